"""Animations of runs: videos (MP4, GIF) and a self-contained HTML viewer (docs/animation.md),
drawn from the result objects they are given: `scene` (the geometry of every frame), `sources`
(the scenes of each kind of result), `video`, `viewer`, and `animate` (`api`)."""

from .api import animate as animate
from .api import scenes_of as scenes_of
from .scene import Body as Body
from .scene import Scene as Scene
