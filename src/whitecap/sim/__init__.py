"""The fluid solver: Position Based Fluids in Taichi, with static, moving and floating obstacles.

Modules: ``runtime`` (Taichi init), ``grid`` (neighbour search, shared with
foam), ``kernels`` (SPH kernels), ``pbf`` (the solver), ``launch`` (its launches as compute graphs), ``obstacles``
(mesh SDF colliders), ``bodies`` (motion laws and rigid bodies), ``driver`` (frames, checkpoints, resume).
"""
