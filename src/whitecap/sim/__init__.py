"""The fluid solver: Position Based Fluids in Taichi, with static obstacles.

Modules: ``runtime`` (Taichi init), ``grid`` (neighbour search, shared with
foam), ``kernels`` (SPH kernels), ``pbf`` (the solver), ``obstacles``
(mesh SDF colliders), ``driver`` (frames, checkpoints, resume).
"""
