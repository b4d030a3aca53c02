"""Animations of runs: videos (MP4, GIF) and a self-contained HTML viewer (docs/animation.md).

Unlike the figures of `jsphere.plots`, which draw the result objects they are given, the
animations read runs from files and replay models (a fit's trials through `compare`, a study's
gaits through `simulate_gaits`), so they sit above the packages that make those runs:
`scene` (the geometry of every frame), `sources` (the runs of each kind of input), `video`,
`viewer`, and `animate`, the entry point of `jsphere animate` (also `jsphere.animate`)."""

from .api import animate as animate
from .api import scenes_of as scenes_of
from .scene import Body as Body
from .scene import Scene as Scene
