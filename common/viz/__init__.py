"""Rerun visualisation of flyslam messages: pure mapping from wire messages to Rerun archetypes.

- :mod:`common.viz.paths` — the entity tree (one place that names every entity) and the blueprint.
- :mod:`common.viz.colours` — fitness → colour, harmonic field → heat-map image (vectorised).
- :mod:`common.viz.logger` — :class:`RerunLogger`, which turns each message into ``rec.log`` calls
  on the right timelines and keeps the little state a view needs (trajectories, the map signature).

Nothing here touches the bus; ``services/bridge.py`` feeds it.
"""
from common.viz.logger import RerunLogger
from common.viz.paths import blueprint

__all__ = ["RerunLogger", "blueprint"]
