"""Every segmenter module; importing this package registers them all.

Each public module here (name not starting with ``_``) registers its segmenters
with ``segmentation.registry.register`` when imported.
"""

import importlib
import pkgutil

for _info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
    if not _info.name.startswith("_"):
        importlib.import_module(f"{__name__}.{_info.name}")
