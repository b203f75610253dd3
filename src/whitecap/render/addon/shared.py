"""whitecap's shared modules: the bpy layer (whitecap/blender), the run reader (io/run.py, its
records in io/record.py: pydantic models, or plain records where Blender's Python has no pydantic) and
SPlisHSPlasH's rigid-body BIN reader (cases/rigid_bin.py, as ``whitecap import`` reads it).

Inside the extension they are the copies ``whitecap blender-addon`` puts in its ``whitecap``
folder; run from whitecap's source tree, whitecap's own.
"""

try:  # inside the extension
    from .whitecap.blender import looks, mesh, place, run  # noqa: F401
    from .whitecap.cases import rigid_bin  # noqa: F401
    from .whitecap.errors import WhitecapError  # noqa: F401
    from .whitecap.io.diffuse_types import COUNT_NAMES, DIFFUSE_RADIUS  # noqa: F401
    from .whitecap.io.record import Obstacle  # noqa: F401
    from .whitecap.io.run import RunInfo  # noqa: F401
except ImportError:
    from whitecap.blender import looks, mesh, place, run  # noqa: F401
    from whitecap.cases import rigid_bin  # noqa: F401
    from whitecap.errors import WhitecapError  # noqa: F401
    from whitecap.io.diffuse_types import COUNT_NAMES, DIFFUSE_RADIUS  # noqa: F401
    from whitecap.io.record import Obstacle  # noqa: F401
    from whitecap.io.run import RunInfo  # noqa: F401
