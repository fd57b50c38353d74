"""The segmentation-vs-drift study: a grid of SLAM runs on simulated bags, and its report.

- ``config``: the experiment YAML (``configs/experiments/*.yaml``), validated on load;
- ``plan``: the grid expanded into cells with content hashes (resume and cache keys);
- ``cell``: one cell (simulate with ``cache``, SLAM on a rig perturbed by ``perturb``,
  evaluate, score the segmenter with ``segeval``) -> one result row;
- ``engine``: cells on a local process pool or a Dask cluster, rows into ``results``;
- ``report``: statistics over seeds, markdown and plots.

Wiring layer: it may import every package of the project.
"""
