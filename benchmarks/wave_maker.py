"""Piston wave maker against linear wave-maker theory (Biésel transfer function).

A piston of stroke S oscillating with period T in water of depth h makes, in
linear theory, progressive waves of height

    H / S = 2 (cosh 2kh − 1) / (sinh 2kh + 2kh),      ω² = g k tanh kh

(Biésel & Suquet 1951; Dean & Dalrymple, *Water Wave Mechanics*, §6.3). This
script runs a narrow (quasi-2D) flume long enough that the reflection from its
far end never reaches the wave gauge within the measured window, records the
free-surface elevation η(t) at the gauge (the median over the particle
columns within a spacing of it of their top particle, plus one radius), and takes H as twice the amplitude of
η's component at ω, fitted over whole periods after the ramp-up.

    PYTHONPATH=src python benchmarks/wave_maker.py [--radius 0.01] [--out benchmarks/wave_maker.png]
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

G = 9.81  # [m/s²]


def wavenumber(T: float, h: float) -> float:
    """k from the linear dispersion relation ω² = g k tanh kh (Newton iterations)."""
    w2 = (2 * math.pi / T) ** 2
    k = w2 / G / math.sqrt(math.tanh(w2 * h / G))  # Eckart's approximation as the start
    for _ in range(50):
        f = G * k * math.tanh(k * h) - w2
        df = G * math.tanh(k * h) + G * k * h / math.cosh(k * h) ** 2
        k -= f / df
    return k


def biesel(T: float, h: float) -> float:
    """H/S of a piston wave maker in linear theory."""
    kh2 = 2 * wavenumber(T, h) * h
    return 2 * (math.cosh(kh2) - 1) / (math.sinh(kh2) + kh2)


def flume_scene(tmp: Path, r: float, h: float, S: float, T: float, length: float, ramp: float,
                solver: dict | None = None):
    import trimesh

    from whitecap.config import scene_from_dict

    width = 4 * r  # two particles across: a quasi-2D flume
    paddle = tmp / "paddle.stl"
    trimesh.creation.box(extents=[0.04, width + 0.04, 2.2 * h]).export(str(paddle))
    x0 = 0.1  # the paddle's rest centre; its face is at x0 + 0.02
    return scene_from_dict({
        "domain": {"upper": [length, width, 2.0 * h]},
        "solver": {"particle_radius": r, "frame_rate": 30.0, **(solver or {})},
        "fluid": [{"lower": [x0 + 0.02, 0.0, 0.0], "upper": [length, width, h]}],
        "obstacle": [{"mesh": str(paddle), "translate": [x0, width / 2, 1.1 * h - 0.01], "friction": 0.0,
                      "motion": {"kind": "piston", "axis": [1, 0, 0], "stroke": S, "period": T, "ramp": ramp}}],
        "foam": {"enabled": False},
    })


def run_flume(r: float = 0.01, h: float = 0.2, S: float = 0.04, T: float = 1.0, length: float = 4.0,
              ramp: float = 1.0, gauge: float = 1.0, duration: float = 5.0, progress: bool = False,
              solver: dict | None = None, gauge_width: float | None = None):
    """(times, η at the gauge, measured H, Biésel H, fitted window, mean level): the flume run and its
    wave height. The gauge reads the particle columns within ``gauge_width`` (default 2r) of it."""
    from whitecap.sim.driver import build_solver

    with tempfile.TemporaryDirectory() as tmp:
        sc = flume_scene(Path(tmp), r, h, S, T, length, ramp, solver)
        s = build_solver(sc)
    x_gauge = 0.12 + gauge
    ts, eta = [], []
    for f in range(1, int(round(duration * 30)) + 1):
        s.advance_frame(f)
        x = s.state.x.to_numpy()
        near = x[np.abs(x[:, 0] - x_gauge) < (gauge_width or 2 * r)]
        cols = np.floor(near[:, 0] / (2 * r)).astype(int) * 1000 + np.floor(near[:, 1] / (2 * r)).astype(int)
        tops = [near[cols == c, 2].max() for c in np.unique(cols)]  # the top particle of each column
        ts.append(s.time)
        eta.append(float(np.median(tops)) + r - h if tops else 0.0)
        if progress and f % 30 == 0:
            print(f"t={s.time:.1f}s  eta={eta[-1]:+.4f} m", file=sys.stderr)
    ts, eta = np.asarray(ts), np.asarray(eta)
    # The window: from when the fully grown wave train has reached the gauge (group velocity),
    # whole periods, ending before the reflection from the far wall comes back.
    k = wavenumber(T, h)
    c = 2 * math.pi / T / k
    cg = 0.5 * c * (1 + 2 * k * h / math.sinh(2 * k * h))
    t0 = ramp + gauge / cg + 0.5 * T
    t_back = (2 * length - 0.12 - x_gauge) / cg
    n_per = int((min(duration, t_back) - t0) // T)
    if n_per < 1:
        raise ValueError("the flume is too short or the run too brief for one clean period at the gauge")
    sel = (ts >= t0) & (ts < t0 + n_per * T)
    w = 2 * math.pi / T
    M = np.stack([np.cos(w * ts[sel]), np.sin(w * ts[sel]), np.ones(sel.sum())], 1)
    a, b, _ = np.linalg.lstsq(M, eta[sel], rcond=None)[0]  # _: the mean level over the window
    return ts, eta, 2 * math.hypot(a, b), biesel(T, h) * S, (t0, t0 + n_per * T), float(_)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--radius", type=float, default=0.01)
    ap.add_argument("--periods", type=float, nargs="+", default=[1.0])
    ap.add_argument("--stroke", type=float, default=0.04)
    ap.add_argument("--depth", type=float, default=0.2)
    ap.add_argument("--iterations", type=int, default=40,
                    help="solver.iterations (PBF needs many for a stiff enough piston response)")
    ap.add_argument("--xsph", type=float, default=0.0, help="solver.xsph_c")
    ap.add_argument("--gauge", type=float, default=0.4, help="distance of the gauge from the paddle [m]")
    ap.add_argument("--out", default=None, help="PNG of η(t) at the gauge with the fitted window")
    a = ap.parse_args(argv)
    from whitecap.sim import runtime

    runtime.init("cpu")
    rows = []
    for T in a.periods:
        ts, eta, H, H_th, win, mean = run_flume(a.radius, a.depth, a.stroke, T, gauge=a.gauge, progress=True,
                                          solver={"iterations": a.iterations, "xsph_c": a.xsph})
        kh = wavenumber(T, a.depth) * a.depth
        rows.append((T, kh, H, H_th))
        print(f"T={T:.2f} s  kh={kh:.2f}  H={H * 1000:.1f} mm  Biésel {H_th * 1000:.1f} mm  "
              f"ratio {H / H_th:.3f}")
        if a.out:
            import matplotlib

            matplotlib.use("Agg")
            import matplotlib.pyplot as plt

            fig, ax = plt.subplots(figsize=(7, 3))
            ax.plot(ts, eta * 1000, lw=1, label=f"η at the gauge ({a.gauge:g} m from the paddle)")
            ax.axvspan(*win, color="0.9", label="fitted window")
            ax.axhline((mean + H_th / 2) * 1000, ls="--", c="k", lw=0.8, label="Biésel ±H/2 about the mean")
            ax.axhline((mean - H_th / 2) * 1000, ls="--", c="k", lw=0.8)
            ax.set_xlabel("t [s]")
            ax.set_ylabel("η [mm]")
            ax.set_title(f"piston S={a.stroke * 100:.0f} cm, T={T} s, h={a.depth} m: H={H * 1000:.1f} mm "
                         f"vs {H_th * 1000:.1f} mm")
            ax.set_ylim(-2 * H_th * 1000, 2 * H_th * 1000)  # the start-up transient of the lattice is clipped
            ax.legend(fontsize=7, loc="upper right", ncol=3)
            fig.tight_layout()
            fig.savefig(a.out, dpi=110)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
