"""Animations of runs: videos (MP4, GIF) and a self-contained HTML viewer (docs/animation.md).

Like the figures of `jsphere.plots`, the animations draw the result objects they are given, and
replay models where a result asks for it (a fit's trials through `compare`, a study's gaits
through `simulate_gaits`): `scene` (the geometry of every frame), `sources` (the scenes of each
kind of result), `video`, `viewer`, and `animate`. `jsphere.animate` (`jsphere.cli.animate`)
reads files into those results first."""

from .api import animate as animate
from .api import scenes_of as scenes_of
from .scene import Body as Body
from .scene import Scene as Scene
