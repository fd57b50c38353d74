"""How many echoes a recording's beams carry: a ``MultiEchoLaserScan`` beam with several echoes
is a surface seen through or past something (glass, an edge, a ghost of the optics), and which
echo is the surface is the run's choice (``input.echo``)."""

from __future__ import annotations

from collections.abc import Sequence

from slam.io.source import MULTIECHO, BagSource

SAMPLE_MESSAGES = 40  # first messages looked at: the echo layout of a recording does not change within it


def several_echoes_share(source: BagSource, topics: Sequence[str], max_messages: int = SAMPLE_MESSAGES) -> float | None:
    """The share of beams with a return that carry more than one echo, over the first
    ``max_messages`` ``MultiEchoLaserScan`` messages of ``topics``; None when none of the topics
    is a ``MultiEchoLaserScan``."""
    kinds = source.topics()
    multi = [t for t in topics if kinds.get(t) == MULTIECHO]
    if not multi:
        return None
    conns = [c for t in multi for c in source.connections(t, MULTIECHO)]
    with_return = several = 0
    for n, (_, _, msg) in enumerate(source.messages(conns)):
        if n >= max_messages:
            break
        counts = [len(e.echoes) for e in msg.ranges]
        with_return += sum(1 for c in counts if c > 0)
        several += sum(1 for c in counts if c > 1)
    return several / with_return if with_return else None
