"""viewloc core: pure algorithms for view-based 6D object localization.

Numpy arrays in, frozen dataclasses out; no HTTP, no files but those passed
in. See DESIGN.md §2 for the pipeline, stage by stage.
"""

from viewloc_core.camera import Camera
from viewloc_core.pose import Pose

__all__ = ["Camera", "Pose"]
