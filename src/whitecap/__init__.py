"""whitecap: particle fluids from simulation to film-quality water.

The Python API mirrors the CLI: ``whitecap.simulate(scene, out=...)``,
``whitecap.foam(...)``, ``whitecap.mesh(...)``, ``whitecap.render(...)``,
``whitecap.run(...)``. Heavy modules load lazily.
"""

import importlib

__version__ = "0.1.0"

_API = ("simulate", "foam", "mesh", "export", "view", "render", "run")


def __getattr__(name):
    if name in _API:
        pipeline = importlib.import_module(".pipeline", __name__)
        if hasattr(pipeline, name):
            return getattr(pipeline, name)
    raise AttributeError(name)
