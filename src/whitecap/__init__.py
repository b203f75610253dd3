"""whitecap: particle fluids from simulation to film-quality water.

The Python API mirrors the CLI: ``whitecap.simulate(scene, out=...)``,
``whitecap.foam(...)``, ``whitecap.mesh(...)``, ``whitecap.render(...)``,
``whitecap.run(...)``. Heavy modules load lazily.
"""

__version__ = "0.1.0"


def __getattr__(name):
    from . import pipeline

    if hasattr(pipeline, name):
        return getattr(pipeline, name)
    raise AttributeError(name)
