"""The in-memory particle frame every reader returns and every writer takes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError


@dataclass(init=False)
class ParticleFrame:
    """One frame of particles, SI units, z up.

    ``positions`` and ``velocities`` are (N, 3) float32; ``ids`` is (N,) uint32
    and stays with a particle across frames (a frame made without them numbers
    its rows 0..N-1); ``density`` is (N,) float32 or None when the source has
    none, as ``velocities`` may be. ``arrays`` holds any other per-particle
    arrays by name (``type``, ``lifetime``, ``radius`` for diffuse particles).

    A frame made by :meth:`from_records` has its arrays as the fields of one record array (``records``), not
    copied: they are strided views, not contiguous ones (``np.ascontiguousarray`` where a contiguous one is
    needed, as for a Taichi kernel). Any other frame has ``records`` None.
    """

    positions: np.ndarray
    velocities: np.ndarray | None
    ids: np.ndarray
    density: np.ndarray | None
    time: float | None
    arrays: dict[str, np.ndarray]
    source: str

    def __init__(
        self,
        positions: np.ndarray,
        velocities: np.ndarray | None = None,
        ids: np.ndarray | None = None,
        density: np.ndarray | None = None,
        time: float | None = None,
        arrays: dict[str, np.ndarray] | None = None,
        source: str = "<memory>",
    ) -> None:
        self.source = source
        self.time = time
        self.positions = np.ascontiguousarray(positions, dtype=np.float32).reshape(-1, 3)
        n = len(self.positions)
        self.velocities = None
        if velocities is not None:
            self.velocities = np.ascontiguousarray(velocities, dtype=np.float32).reshape(-1, 3)
            self._check_len("velocity", self.velocities)
        if ids is None:
            self.ids = np.arange(n, dtype=np.uint32)
        else:
            self.ids = np.ascontiguousarray(ids, dtype=np.uint32).reshape(-1)
            self._check_len("id", self.ids)
        self.density = None
        if density is not None:
            self.density = np.ascontiguousarray(density, dtype=np.float32).reshape(-1)
            self._check_len("density", self.density)
        self.arrays = {} if arrays is None else arrays
        for k, a in self.arrays.items():
            self._check_len(k, a)
        # the record array the arrays are the fields of (from_records), else None: not a field of the dataclass, so
        # that a frame made from this one (dataclasses.replace) does not carry it
        self.records: np.ndarray | None = None

    #: the fields from_records reads as vectors, and where each goes; ``id`` and ``density`` go to their own
    _VECTORS = (("x", "y", "z"), ("vx", "vy", "vz"))

    @classmethod
    def from_records(cls, records: np.ndarray, time: float | None = None, source: str = "<memory>") -> "ParticleFrame":
        """A frame whose arrays are views of the fields of ``records`` (a 1-D structured array: x y z float32 side by
        side, then optionally vx vy vz, density, id and any others, which go to ``arrays`` in their order), kept as
        ``records``: nothing is copied, and the PLY writer writes the records as they are where their layout is its
        own (io.ply.record_dtype)."""
        names = records.dtype.names or ()
        fields = records.dtype.fields or {}
        vectors: list[np.ndarray | None] = []
        for trio in cls._VECTORS:
            if trio[0] not in names:
                vectors.append(None)
                continue
            off = fields[trio[0]][1]
            if any(fields.get(k) != (np.dtype("<f4"), off + 4 * c) for c, k in enumerate(trio)):
                raise ValueError(f"records: {' '.join(trio)} are not float32 side by side")
            vec = np.dtype({"names": ["v"], "formats": [("<f4", (3,))], "offsets": [off],
                            "itemsize": records.dtype.itemsize})
            vectors.append(records.view(vec)["v"])
        if vectors[0] is None:
            raise ValueError("records: no x y z")
        taken = {k for trio in cls._VECTORS for k in trio} | {"id", "density"}
        frame = cls.__new__(cls)
        frame.source, frame.time = source, time
        frame.positions, frame.velocities = vectors[0], vectors[1]  # type: ignore[assignment]
        frame.ids = records["id"] if "id" in names else np.arange(len(records), dtype=np.uint32)
        frame.density = records["density"] if "density" in names else None
        frame.arrays = {k: records[k] for k in names if k not in taken}
        frame.records = records
        return frame

    def __len__(self) -> int:
        return len(self.positions)

    def _check_len(self, name: str, a: np.ndarray) -> None:
        if len(a) != len(self.positions):
            raise InputError(
                f"{self.source}: array '{name}' has {len(a)} entries but there are {len(self.positions)} positions"
            )

    def check_finite(self) -> None:
        """Raise InputError naming the file if any position or velocity is NaN/inf."""
        for name, a in (("positions", self.positions), ("velocities", self.velocities)):
            if a is not None and not np.isfinite(a).all():
                bad = int((~np.isfinite(a).all(axis=1)).sum())
                raise InputError(f"{self.source}: {name}: {bad} particles are NaN or infinite")

    def sorted_by_id(self) -> "ParticleFrame":
        """The same particles with rows in increasing ``id`` order.

        Solvers that reorder their particles for cache efficiency (SPlisHSPlasH
        z-sorts them every step) write a different row order in every frame;
        sorting by the persistent id gives every frame the same order, so row i
        is one particle throughout. Raises InputError naming the file when two
        rows share an id."""
        order = np.argsort(self.ids, kind="stable")
        ids = self.ids[order]
        if len(ids) > 1 and (dup := np.flatnonzero(ids[1:] == ids[:-1])).size:
            raise InputError(f"{self.source}: id: {dup.size} ids appear more than once (e.g. {int(ids[dup[0]])})")
        return ParticleFrame(
            positions=self.positions[order],
            velocities=None if self.velocities is None else self.velocities[order],
            ids=ids,
            density=None if self.density is None else self.density[order],
            time=self.time,
            arrays={k: a[order] for k, a in self.arrays.items()},
            source=self.source,
        )
