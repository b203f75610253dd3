#!/usr/bin/env python3
"""Mutation audit: how many deliberate one-line bugs do the tests catch?

Each mutation below is a small, realistic bug (a sign flip, an off-by-one, a wrong
axis, a dropped term, a wrong order of composition, a list position used for a
frame index, ...) in one file of ``src/whitecap``. For each, this script

1. copies the repository (src/, tests/, scenes/, ...) once into a temporary
   directory, so the working tree is never modified;
2. applies the mutation to the copy (the original snippet must occur exactly once;
   a snippet that is no longer in the file is reported as STALE);
3. runs the test files that cover that code there (``pytest -x -q``, with
   ``PYTHONPATH`` pointing the import of ``whitecap`` at the copy's src/) under a
   per-mutation timeout;
4. restores the file and reports CAUGHT (a test failed), SURVIVED (all passed),
   TIMEOUT or ERROR (pytest could not run: collection or usage error).

The catch rate is CAUGHT / (all mutations that applied). A survivor is a bug no test
would see: add a test that fails under it (and passes on the real code), or explain
why the mutation is equivalent.

    .venv/bin/python scripts/mutation_audit.py                 # every mutation
    .venv/bin/python scripts/mutation_audit.py --list          # names, files, covering tests
    .venv/bin/python scripts/mutation_audit.py --only body-inertia-world-frame --only usd-fps
    .venv/bin/python scripts/mutation_audit.py --tests-rev 8b5132d   # the tests of a past commit
    .venv/bin/python scripts/mutation_audit.py --check         # the unmutated copy must pass first
    .venv/bin/python scripts/mutation_audit.py --src-rev 8b5132d --tests-rev 8b5132d \
        --overlay tests/test_physics_audit.py                   # one new test file on an old commit

Options: ``--timeout`` seconds per mutation (default 900), ``--src-rev REV`` to audit
the source of a commit instead of the working tree, ``--tests-rev REV`` to use the
tests of a commit (a baseline), ``--json FILE`` for machine-readable results,
``--logs DIR`` to keep each mutation's pytest output.

A whole audit runs the covering files once per mutation, one mutation at a time: about
30-45 minutes on 2 cores (a caught mutation stops at its first failing test, so the fast
*_audit.py files come first in each list). Use ``--check`` when the tree may hold work in
progress: a test that already fails would otherwise "catch" every mutation.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tarfile
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Mutation:
    name: str
    file: str  # relative to src/whitecap
    old: str  # exact snippet; must occur exactly once
    new: str
    tests: tuple  # test files (or node ids) that cover the code, fastest-failing first
    what: str = ""


def M(name, file, old, new, tests, what=""):
    return Mutation(name, file, old, new, tuple(tests), what)


# Test files, fastest first where one mutation names several.
PHYS = "tests/test_physics_audit.py"
IOA = "tests/test_io_audit.py"
VIEWA = "tests/test_view_audit.py"
DIFFA = "tests/test_diffuse_audit.py"
SURFA = "tests/test_surface_audit.py"

MUTATIONS: list[Mutation] = [
    # ------------------------------------------------------------------ sim/
    M("obstacle-density-gradient", "sim/obstacles.py",
      "                    grad_psi[i] += gp\n", "                    grad_psi[i] += 0.0 * gp\n",
      [PHYS, "tests/test_obstacles.py"], "an obstacle's density share without its gradient"),
    M("obstacle-density-share-overwrites-walls", "sim/obstacles.py",
      "psi[i] += (1.0 - f) * psi_table[k] + f * psi_table[k + 1]",
      "psi[i] = (1.0 - f) * psi_table[k] + f * psi_table[k + 1]",
      [PHYS, "tests/test_obstacles.py"], "the obstacle's share replaces the walls' instead of adding to it"),
    M("obstacle-normal-not-rotated", "sim/obstacles.py",
      "nrm = rot[o] @ g.normalized()", "nrm = g.normalized()",
      [PHYS, "tests/test_bodies.py"], "contact response along the rest-frame normal of a turned body"),
    M("body-inertia-world-frame", "sim/bodies.py",
      "I = R @ self.I0 @ R.T", "I = self.I0",
      [PHYS, "tests/test_bodies.py"], "inertia tensor not rotated into the world frame"),
    M("body-quaternion-update-order", "sim/bodies.py",
      "q = self.q + 0.5 * dt * quat_mul(np.array([0.0, *self.W]), self.q)",
      "q = self.q + 0.5 * dt * quat_mul(self.q, np.array([0.0, *self.W]))",
      [PHYS, "tests/test_bodies.py"], "world angular velocity applied in the body frame (wrong composition)"),
    M("body-gyroscopic-sign", "sim/bodies.py",
      "self.W = self.W + dt * np.linalg.solve(I, self.tau - np.cross(self.W, I @ self.W))",
      "self.W = self.W + dt * np.linalg.solve(I, self.tau + np.cross(self.W, I @ self.W))",
      [PHYS, "tests/test_bodies.py"], "Euler's equations with the gyroscopic term's sign flipped"),
    M("body-reaction-torque-lever", "sim/bodies.py",
      "self.tau = -(moment - np.cross(self.c, impulse)) / dt",
      "self.tau = -(moment + np.cross(self.c, impulse)) / dt",
      [PHYS, "tests/test_bodies.py"], "fluid torque moved to the centre of mass with the wrong sign"),
    M("body-wall-contact-no-rotation", "sim/bodies.py",
      "inv_m = self.t_free[w % 3] / self.mass + (rn * a).sum(1)",
      "inv_m = self.t_free[w % 3] / self.mass + 0.0 * (rn * a).sum(1)",
      [PHYS, "tests/test_bodies.py"], "effective mass of a wall contact without its rotational part"),
    M("keyframes-from-t0", "sim/bodies.py",
      "u = (t - times[j]) / (times[j + 1] - times[j])", "u = t / (times[j + 1] - times[j])",
      [PHYS, "tests/test_bodies.py"], "keyframe interpolation that assumes the segment starts at t = 0"),
    M("keyframes-centre-origin", "sim/bodies.py",
      "c = np.asarray(m.centre if m.centre is not None else self.o.translate, np.float64)",
      "c = np.asarray(m.centre if m.centre is not None else [0.0, 0.0, 0.0], np.float64)",
      [PHYS, "tests/test_bodies.py"], "keyframe rotations about the origin, not the obstacle's position"),
    M("step-velocity-order", "sim/bodies.py",
      "Q = R0 @ R1.T", "Q = R1 @ R0.T", ["tests/test_bodies.py"], "body velocity from the inverse rotation"),
    M("spin-about-origin", "sim/bodies.py",
      "R = axis_rotation(m.axis, 2.0 * math.pi * m.rpm / 60.0 * t)\n"
      "            c = np.asarray(m.centre, np.float64)\n            return R, c - R @ c",
      "R = axis_rotation(m.axis, 2.0 * math.pi * m.rpm / 60.0 * t)\n"
      "            c = np.asarray(m.centre, np.float64)\n            return R, R @ c - c",
      ["tests/test_bodies.py"], "spin about the centre with the translation's sign flipped"),
    M("euler-order", "geometry.py",
      "return axis_rotation([0, 0, 1], rz) @ axis_rotation([0, 1, 0], ry) @ axis_rotation([1, 0, 0], rx)",
      "return axis_rotation([1, 0, 0], rx) @ axis_rotation([0, 1, 0], ry) @ axis_rotation([0, 0, 1], rz)",
      [PHYS, "tests/test_bodies.py"], "keyframe rotation composed z, y, x instead of x, y, z"),
    M("pbf-upper-wall-gradient-sign", "sim/pbf.py",
      "            g[a] -= lookup(dpsi_table, d_hi, h)", "            g[a] += lookup(dpsi_table, d_hi, h)",
      [PHYS, "tests/test_solver.py"], "the upper walls' density gradient points out of the fluid"),
    # (Dropping |∇_i C_i|² from λ's denominator was tried and left out: ∇_i C_i ≈ 0 inside the fluid
    # and C_i = 0 at its free surface, so λ hardly changes; measured, no difference in a settled
    # tank's speeds, compression or wall layer beyond 0.1 ‰. An equivalent mutant tells nothing.)
    M("pbf-constraint-unclamped", "sim/pbf.py",
      "c = ti.max(rho_i / rho0 - 1.0, 0.0)", "c = rho_i / rho0 - 1.0",
      ["tests/test_solver.py"], "the density constraint pulls under-dense particles together"),
    M("pbf-scorr-sign", "sim/pbf.py",
      "acc += (li + lam[j] - scorr_k * qn)", "acc += (li + lam[j] + scorr_k * qn)",
      ["tests/test_solver.py"], "tensile correction pulling instead of pushing"),
    M("pbf-vorticity-cross-order", "sim/pbf.py",
      "v[i] += dt * eps * (eta / ln).cross(omega[i])", "v[i] += dt * eps * omega[i].cross(eta / ln)",
      ["tests/test_solver.py"], "vorticity confinement force N × ω reversed"),
    M("grid-corner-cut-off-by-one", "sim/grid.py",
      "ey = ti.select(dy > 0, reach * w - f.y, (reach - 1) * w + f.y)",
      "ey = ti.select(dy > 0, reach * w - f.y, reach * w + f.y)",
      ["tests/test_grid.py"], "outer y columns cut one cell too eagerly"),
    M("kernel-spiky-sign", "sim/smoothing.py",
      "        self.spiky = -45.0 / (math.pi * h**6)", "        self.spiky = 45.0 / (math.pi * h**6)",
      ["tests/test_solver.py"], "spiky gradient pointing inwards"),
    # ------------------------------------------------------------------ diffuse/
    M("budget-ignores-live", "diffuse/budget.py",
      "room = budget * n_fluid - alive", "room = budget * n_fluid",
      [DIFFA, "tests/test_budget.py", "tests/test_diffuse.py"], "the budget's room ignoring the particles alive"),
    M("auto-rescales-explicit-k", "diffuse/generator.py",
      'return self.p.auto and not ({"k_ta", "k_wc", "k_vo"} & self.p.explicit)', "return self.p.auto",
      [DIFFA, "tests/test_budget.py", "tests/test_diffuse.py"], "'auto' rescales k values the user set"),
    M("ini-values-not-explicit", "diffuse/params.py",
      "explicit |= set(f.params) | set(f.joules)", "explicit |= set(f.joules)",
      [DIFFA, "tests/test_budget.py", "tests/test_diffuse.py"], "'auto' overrides thresholds an .ini set"),
    M("budget-phi-below-tmin", "diffuse/budget.py",
      "return (np.minimum(i, tmax) - np.minimum(i, tmin)) / (tmax - tmin)",
      "return (np.minimum(i, tmax) - tmin) / (tmax - tmin)",
      [DIFFA, "tests/test_budget.py", "tests/test_diffuse.py"], "φ negative below τmin"),
    M("budget-top-sample-strided", "diffuse/budget.py",
      "at_random = _sample_places(len(values))",
      "at_random = slice(None, None, max(1, len(values) // TOP_SAMPLE))",
      ["tests/test_budget.py"], "the percentiles' bound from every k-th value (aliased with a lattice's period)"),
    M("budget-running-window-off-by-one", "diffuse/budget.py",
      "first = np.maximum(x - w, 0)", "first = np.maximum(x - w - 1, 0)",
      [DIFFA, "tests/test_budget.py", "tests/test_diffuse.py"], "running peak's window one frame too long"),
    M("budget-survival-reversed", "diffuse/budget.py",
      "alive = np.clip((hi - ages) / (hi - lo), 0.0, 1.0)", "alive = np.clip((ages - lo) / (hi - lo), 0.0, 1.0)",
      [DIFFA, "tests/test_budget.py", "tests/test_diffuse.py"], "survival rising with age"),
    M("budget-rescale-correction-inverted", "diffuse/budget.py",
      "c = float(np.clip(alive / model, 1 / CORRECTION_LIMIT, CORRECTION_LIMIT))",
      "c = float(np.clip(model / alive, 1 / CORRECTION_LIMIT, CORRECTION_LIMIT))",
      [DIFFA, "tests/test_budget.py", "tests/test_diffuse.py"], "survival correction the wrong way up"),
    M("crest-convexity-sign", "diffuse/kernels.py",
      "take = (r > 0.0) & (r < h) & (xji.dot(ni) < 0.0)", "take = (r > 0.0) & (r < h) & (xji.dot(ni) > 0.0)",
      ["tests/test_diffuse.py"], "wave crests from concave neighbours"),
    M("spray-boundary", "diffuse/kernels.py",
      "    if cnt < spray_below:\n        t = SPRAY", "    if cnt <= spray_below:\n        t = SPRAY",
      [DIFFA, "tests/test_diffuse.py"], "a particle with exactly spray_below neighbours is spray"),
    M("bubble-boundary", "diffuse/kernels.py",
      "    elif cnt > bubble_above:\n        t = BUBBLE", "    elif cnt >= bubble_above:\n        t = BUBBLE",
      [DIFFA, "tests/test_diffuse.py"], "a particle with exactly bubble_above neighbours is a bubble"),
    M("bubble-buoyancy-sign", "diffuse/kernels.py",
      "vd[p] += dt * (-k_b * g) + k_d * (vf - vd[p])", "vd[p] += dt * (k_b * g) + k_d * (vf - vd[p])",
      ["tests/test_diffuse.py"], "bubbles sink"),
    M("spray-restitution-sign", "diffuse/kernels.py",
      "vp = u + vr - (1.0 + SPRAY_RESTITUTION) * vn * nrm", "vp = u + vr - (1.0 - SPRAY_RESTITUTION) * vn * nrm",
      ["tests/test_bodies.py", "tests/test_obstacles.py"], "spray bounce with the restitution subtracted"),
    M("diffuse-obstacle-pose-inverse", "sim/obstacles.py",
      "return self.grid.sample((np.asarray(pts, np.float64) - T) @ R)  # x_rest = Rᵀ(x − T)",
      "return self.grid.sample((np.asarray(pts, np.float64) - T) @ R.T)  # x_rest = Rᵀ(x − T)",
      ["tests/test_bodies.py"], "diffuse particles tested against the body at its inverse rotation"),
    M("diffuse-obstacles-skipped-for-foam", "diffuse/kernels.py",
      "                    if d <= 0.0:\n                        if t == BUBBLE:",
      "                    if d <= 0.0 and t != FOAM:\n                        if t == BUBBLE:",
      [PHYS, "tests/test_obstacles.py", "tests/test_bodies.py"],
      "foam that ends a frame inside an obstacle stays there"),
    M("diffuse-body-pose-a-frame-late", "diffuse/driver.py",
      "g.at_frame(t, info.body_pose(index, g.index), 0.0 if first else dt,",
      "g.at_frame(t, info.body_pose(max(index - 1, 0), g.index), 0.0 if first else dt,",
      ["tests/test_bodies.py"], "diffuse particles tested against the body where it was a frame before"),
    # ------------------------------------------------------------------ io/
    M("usd-fps", "export/usd.py",
      "    stage.SetFramesPerSecond(cache.frame_rate)\n", "",
      [IOA, "tests/test_export_usd.py"], "the USD stage's framesPerSecond not set"),
    M("usd-body-op-order", "export/usd.py",
      "move, turn = m.AddTranslateOp(), m.AddOrientOp(UsdGeom.XformOp.PrecisionDouble)",
      "turn, move = m.AddOrientOp(UsdGeom.XformOp.PrecisionDouble), m.AddTranslateOp()",
      ["tests/test_export_usd.py"], "a body's pose composed R·T instead of T·R"),
    M("atomic-temp-left", "io/atomic.py",
      "        if tmp_path.exists():\n            tmp_path.unlink()", "        if tmp_path.exists():\n            pass",
      [IOA, "tests/test_io.py"], "a failed atomic write leaves its temporary file"),
    M("atomic-error-names-temp", "io/atomic.py",
      "raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from exc", "raise",
      [IOA, "tests/test_io.py", "tests/test_errors.py"], "a disk-full error names the temporary file"),
    M("y-up-improper-rotation", "io/axes.py",
      "np.stack([a[:, 0], -a[:, 2], a[:, 1]], axis=1)", "np.stack([a[:, 0], a[:, 2], a[:, 1]], axis=1)",
      ["tests/test_io.py"], "y-up data mirrored instead of rotated"),
    M("ply-velocity-axes", "io/ply.py",
      'vel = _vectors(v, ("vx", "vy", "vz"))', 'vel = _vectors(v, ("vx", "vz", "vy"))',
      ["tests/test_io.py"], "PLY velocities read with y and z swapped"),
    M("sequence-order-by-name", "io/sequence.py",
      "    return sorted(frames.items())", "    return list(frames.items())",
      ["tests/test_view.py", "tests/test_io.py"], "frames in file-name order instead of frame order"),
    M("run-entry-bisect-right", "io/run.py",
      'k = bisect.bisect_left(fr, index, key=lambda e: e.index)',
      'k = bisect.bisect_right(fr, index, key=lambda e: e.index)',
      ["tests/test_run_integrity.py"], "a frame entry looked up one past its place"),
    M("sort-by-id-drops-velocity-order", "io/frame.py",
      "velocities=None if self.velocities is None else self.velocities[order],",
      "velocities=self.velocities,",
      ["tests/test_cases_splishsplash.py", "tests/test_io.py"], "ids sorted but velocities left in file order"),
    # ------------------------------------------------------------------ cases/
    M("dsph-floating-type", "cases/dualsphysics.py",
      "MOVING_TYPES = (1, 2)", "MOVING_TYPES = (1,)",
      [IOA, "tests/test_cases_dualsphysics.py"], "a Type-2 (floating) body static unless the XML says so"),
    M("rigid-fit-by-list-order", "cases/dualsphysics.py",
      "poses.append(fit_pose(rest[ia], pos[ib], poses[-1] if poses else None))",
      "poses.append(fit_pose(rest, pos, poses[-1] if poses else None))",
      [IOA, "tests/test_cases_dualsphysics.py"], "particles matched by list order instead of Idp"),
    M("kabsch-reflection-guard", "cases/rigid_fit.py",
      "d = 1.0 if np.linalg.det(Vt.T @ U.T) >= 0 else -1.0", "d = 1.0",
      ["tests/test_cases_dualsphysics.py"], "best orthogonal fit may be a reflection"),
    M("kabsch-translation", "cases/rigid_fit.py",
      "return R, q_bar - R @ p_bar", "return R, q_bar - p_bar",
      ["tests/test_cases_dualsphysics.py"], "translation of the centroids without the rotation"),
    M("quaternion-continuity-sign", "cases/rigid_fit.py",
      'if previous is not None and float(np.dot(q, previous.quaternion)) < 0:',
      'if previous is not None and float(np.dot(q, previous.quaternion)) > 0:',
      [IOA, "tests/test_cases_dualsphysics.py"], "consecutive quaternions take the long way round"),
    # ------------------------------------------------------------------ surface/
    M("wall-snap-distance-sign", "surface/reconstruct.py",
      "d = (coord - v[:, axis]) * side", "d = (v[:, axis] - coord) * side",
      [SURFA, "tests/test_surface.py"], "distance to a wall measured from its far side"),
    M("walls-from-run-side", "surface/reconstruct.py",
      'axis, side = "xyz".index(w[0]), (1 if w[1] == "+" else -1)',
      'axis, side = "xyz".index(w[0]), (1 if w[1] == "-" else -1)',
      [SURFA, "tests/test_surface.py"], "upper and lower walls swapped"),
    M("canonical-order-flips-winding", "surface/reconstruct.py",
      "    f = rank[faces]\n", "    f = rank[faces[:, ::-1]]\n",
      ["tests/test_surface.py"], "canonical order reverses every triangle's winding"),
    # ------------------------------------------------------------------ view/
    M("playback-frame-by-position", "view/sources.py",
      "        idx = self.indices[k]\n", "        idx = k\n",
      [VIEWA, "tests/test_view.py"], "playback uses a frame's list position as its index"),
    M("web-surface-by-position", "view/web.py",
      "            self._draw_surface(fr.index)", "            self._draw_surface(st.frame)",
      [VIEWA, "tests/test_view_web.py"], "the web viewer's surface of the list position, not the frame"),
    M("playback-loop-off-by-one", "view/app.py",
      "        if nxt >= len(source):", "        if nxt > len(source):",
      ["tests/test_view.py"], "playback runs one frame past the end before looping"),
    M("posed-normals-inverse", "view/geometry.py",
      "(normals @ R.T).astype(np.float32)", "(normals @ R).astype(np.float32)",
      [VIEWA, "tests/test_view.py", "tests/test_bodies.py"], "a turned body's normals turned the other way"),
    M("colormap-reversed-weight", "view/colors.py",
      "return ((1 - w) * COLORMAP_STOPS[i] + w * COLORMAP_STOPS[i + 1]).astype(np.float32)",
      "return (w * COLORMAP_STOPS[i] + (1 - w) * COLORMAP_STOPS[i + 1]).astype(np.float32)",
      [VIEWA, "tests/test_view.py"], "colour map interpolates each segment backwards"),
    # ------------------------------------------------------------------ a check on the others
    # Added after the tests above were written, as a check that the suite catches mutations it was
    # not written against (the target is about other mutations as well as these).
    M("piston-cosine", "sim/bodies.py",
      "return self._ramp(m, t) * 0.5 * m.stroke * math.sin(", "return self._ramp(m, t) * 0.5 * m.stroke * math.cos(",
      [PHYS, "tests/test_bodies.py"], "a piston that starts at full stroke"),
    M("flap-hinge-sign", "sim/bodies.py",
      "return R, p - R @ p", "return R, p + R @ p", [PHYS, "tests/test_bodies.py"], "a flap whose hinge moves"),
    M("wall-contact-velocity-sign", "sim/bodies.py",
      "                if un < 0.0:", "                if un > 0.0:",
      [PHYS, "tests/test_bodies.py"], "wall impulses stop a body moving away from the wall"),
    M("wall-depth-lower-sign", "sim/bodies.py",
      "depth = np.concatenate([self.lo - verts, verts - self.hi], axis=1)",
      "depth = np.concatenate([verts - self.lo, verts - self.hi], axis=1)",
      [PHYS, "tests/test_bodies.py"], "depth past the lower walls measured the wrong way"),
    M("wall-friction-inverted", "sim/pbf.py",
      "vi *= 1.0 - wall_friction", "vi *= wall_friction", ["tests/test_solver.py"], "wall friction keeps 1 − f of it"),
    M("xsph-sign", "sim/pbf.py",
      "v_out[i] = v[i] + c * acc", "v_out[i] = v[i] - c * acc", ["tests/test_solver.py"], "XSPH amplifies shear"),
    M("birth-velocity-no-spread", "diffuse/kernels.py",
      "return x_f + off + xh * dt * vl * vh, off + v_f, life", "return x_f + off + xh * dt * vl * vh, v_f, life",
      [DIFFA, "tests/test_diffuse.py"], "new particles without their spread"),
    M("trapped-air-sign", "diffuse/kernels.py",
      "vl * (1.0 - (vij / ti.select(moving, vl, 1.0)).dot(xh))",
      "vl * (1.0 + (vij / ti.select(moving, vl, 1.0)).dot(xh))",
      [DIFFA, "tests/test_diffuse.py"], "trapped air from separating instead of colliding fluid"),
    M("tau-max-from-lower-percentile", "diffuse/budget.py",
      "tau[2 * k + 1] = max(float(hi), 2 * tmin)", "tau[2 * k + 1] = max(float(lo), 2 * tmin)",
      [DIFFA, "tests/test_budget.py", "tests/test_diffuse.py"], "'auto' τmax from the lower percentile"),
    M("history-merge-drops-frames", "diffuse/budget.py",
      "frames, stride = frames[0::2] + frames[1::2], 2 * stride", "frames, stride = frames[0::2], 2 * stride",
      [DIFFA, "tests/test_budget.py"], "merged history rows count half their frames"),
    M("run-truncate-drops-last", "io/run.py",
      'if f.index <= last_index', 'if f.index < last_index',
      ["tests/test_run_integrity.py", "tests/test_solver.py"], "resume forgets the last finished frame"),
    M("container-smallest-box", "cases/dualsphysics.py",
      "if inside.mean() >= CONTAINER_FLUID_FRACTION and vol > best_vol",
      "if inside.mean() >= CONTAINER_FLUID_FRACTION and vol < best_vol",
      [IOA, "tests/test_cases_dualsphysics.py"], "the container chosen by the wrong box size"),
    M("surface-radius-unscaled", "surface/reconstruct.py",
      "particle_radius=self.surface_radius,", "particle_radius=self.particle_radius,",
      ["tests/test_surface.py"], "splashsurf given r instead of the surface radius"),
    M("camera-yaw-axes", "view/state.py",
      "cp * math.sin(self.yaw)", "cp * math.cos(self.yaw)", [VIEWA, "tests/test_view.py"], "orbit camera off its yaw"),
    M("free-fall-speed-half", "view/colors.py",
      "return float(np.sqrt(2.0 * GRAVITY * max(height, 0.0)))", "return float(np.sqrt(GRAVITY * max(height, 0.0)))",
      [VIEWA, "tests/test_view.py"], "the speed colour range from half the fall height"),
    # ------------------------------------------------------------------ issue 31's machinery (the diffuse state on the
    # device, the hashed cell table, records made on the device, the background writer, the host arrays' pool)
    M("scan-inclusive", "sim/scan.py",
      "            c = a[j]\n            out[j] = s\n            s += c",
      "            c = a[j]\n            s += c\n            out[j] = s",
      ["tests/test_diffuse_compaction.py"], "the compaction's places from an inclusive prefix sum"),
    M("scan-grouped-offset-dropped", "sim/scan.py",
      "            s += sums[nb + 1 + b // SCAN_GROUP]", "            s += 0",
      ["tests/test_diffuse_compaction.py"], "a GPU's scan without its groups' offsets"),
    M("compaction-in-place", "diffuse/kernels.py",
      "        if keep[p]:\n            q = pos[p]\n", "        if keep[p]:\n            q = p\n",
      ["tests/test_diffuse_compaction.py"], "survivors left at their old rows (holes, the last ones lost)"),
    M("new-ids-per-chunk", "diffuse/kernels.py",
      "oids[q] = next_id + ti.cast(rank_base + rank[j], ti.u32)", "oids[q] = next_id + ti.cast(rank[j], ti.u32)",
      ["tests/test_diffuse_compaction.py", "tests/test_diffuse_generate.py"],
      "new particles' ids counted from each chunk's start (the same ids in two chunks)"),
    M("room-per-chunk", "diffuse/kernels.py",
      "if kind[j] >= 0 and rank_base + rank[j] < room:", "if kind[j] >= 0 and rank[j] < room:",
      ["tests/test_diffuse_compaction.py", "tests/test_diffuse_generate.py"],
      "the capacity's room checked within each chunk, not the frame"),
    M("next-id-not-advanced", "diffuse/generator.py",
      "            st.next_id += min(nk, room)\n", "            st.next_id += 0\n",
      ["tests/test_diffuse_compaction.py"], "the next frame's new particles take this frame's ids again"),
    M("records-split-field-shift", "sim/records.py",
      "                                word |= bits >> ti.u32(-shift)",
      "                                word |= bits << ti.u32(-shift)",
      ["tests/test_diffuse_memory.py", "tests/test_background_writer.py"],
      "a field split across two words shifted the wrong way in its second word"),
    M("records-radius-unscaled", "diffuse/generator.py",
      "radius_bits = int(np.float32(self.p.radius * self.r).view(np.uint32))",
      "radius_bits = int(np.float32(self.p.radius).view(np.uint32))",
      ["tests/test_diffuse_memory.py", "tests/test_background_writer.py", "tests/test_diffuse.py"],
      "the diffuse file's radius in units of r, not metres"),
    M("hashed-other-cells-offered", "sim/grid.py",
      "_offer(g, s, ti.select(mine, (q - ps[g]).norm_sqr(), FAR2), h2, task, args, every_candidate)",
      "_offer(g, s, (q - ps[g]).norm_sqr(), h2, task, args, every_candidate)",
      ["tests/test_grid.py"], "a hashed bucket's other cells' particles taken as neighbours (twice, or from afar)"),
    M("hashed-wrap-lost", "sim/grid.py",
      "    if b1 < b0:  # wrapped round the table's end: slots n.. stand for 0..\n        last += n\n",
      "    if b1 < b0:  # wrapped round the table's end: slots n.. stand for 0..\n        last += 0\n",
      ["tests/test_grid.py"], "a column whose buckets wrap round the table's end loses its head"),
    M("hashed-upper-border-closed", "sim/grid.py",
      "    hi = ti.select(ivec3(cx, cy, z1) == dims - 1, far, hi)\n", "",
      ["tests/test_grid.py"], "points beyond the domain's upper faces found by no hashed query"),
    M("pool-reuses-held-block", "io/array_pool.py",
      "        return all(r <= free for r, free in zip(self._refs(block), block.free_refs))", "        return True",
      ["tests/test_array_pool.py", "tests/test_diffuse_memory.py"], "a frame still held written over by the next"),
    M("buffers-grow-exactly", "diffuse/generator.py",
      "            rows = max(size, 2 * a.shape[0] if a is not None else start, 1)",
      "            rows = max(size, start, 1)",
      ["tests/test_diffuse_memory.py"], "kept arrays grown to each frame's size (a new array every growing frame)"),
    M("live-arrays-grow-exactly", "diffuse/generator.py",
      "        rows = _outgrown(rows, held)", "        rows = _outgrown(rows, 0)",
      ["tests/test_diffuse_memory.py"], "the live particles' arrays made anew every frame of an inflow"),
    M("writer-listing-before-files", "io/writer.py",
      "        fut = self._ordered.submit(self._job, box, label, before)",
      "        fut = self._ordered.submit(self._job, box, label, ())",
      ["tests/test_background_writer.py"], "run.json written while the frame's files are still being written"),
    M("writer-goes-on-after-error", "io/writer.py",
      "        if self._error is None:  # else skipped", "        if True:  # else skipped",
      ["tests/test_background_writer.py"], "a run.json listing a file whose write failed"),
    M("writer-lanes-wait-for-listing", "io/writer.py",
      "        fut = pool.submit(self._job, box, label, ())",
      "        fut = pool.submit(self._job, box, label, self._in_flight())",
      ["tests/test_background_writer.py"], "the next frame's files wait for the last frame's run.json"),
    M("writer-lane-one-thread", "io/writer.py",
      "            pool = ThreadPoolExecutor(self._depth, ", "            pool = ThreadPoolExecutor(1, ",
      ["tests/test_background_writer.py"], "a lane writes one file at a time whatever its depth"),
    M("writer-counts-on-a-lane", "diffuse/driver.py",
      'writer.submit(functools.partial(write_text, out / COUNTS_CSV, csv), "counts")',
      'writer.submit(functools.partial(write_text, out / COUNTS_CSV, csv), "counts", lane="counts")',
      ["tests/test_background_writer.py"], "counts.csv listing a frame whose diffuse file is still being written"),
    M("advection-waited-for-holding-the-gil", "diffuse/generator.py",
      "        runtime.device_idle()\n\n    # " + "-" * 66 + " obstacles",
      "        pass\n\n    # " + "-" * 66 + " obstacles",
      ["tests/test_background_writer.py"],
      "on a GPU, generation's first read-back waits for the advection holding the GIL"),
    M("classification-waited-for-holding-the-gil", "diffuse/generator.py",
      "    runtime.device_idle()\n    return np.array(K.tally_kinds", "    return np.array(K.tally_kinds",
      ["tests/test_background_writer.py"],
      "on a GPU, the count of the kept waits for a chunk's classification holding the GIL"),
    M("potentials-waited-for-holding-the-gil", "diffuse/generator.py",
      "                runtime.device_idle()  # the lists and potentials",
      "                pass  # the lists and potentials",
      ["tests/test_background_writer.py"], "on a GPU, the crests' count waits for the potentials holding the GIL"),
    M("no-checkpoint-at-the-last-frame", "sim/driver.py",
      "            if index % interval == 0 or index == nframes:", "            if index % interval == 0:",
      ["tests/test_background_writer.py", "tests/test_frame_hooks.py"],
      "a run whose frames are not a multiple of the checkpoint interval ends without a checkpoint of its last frame"),
    M("dense-table-for-any-domain", "sim/grid.py",
      "    if nc <= max(DENSE_CELLS_PER_PARTICLE * int(capacity), DENSE_ALWAYS_CELLS) and nc < 2**31 - 1:",
      "    if nc < 2**31 - 1:",
      ["tests/test_grid.py", "tests/test_coast_scene.py"], "a dense cell table for a domain 1000 times the fluid"),
    M("list-slots-past-int32", "sim/grid.py",
      "    fit = MAX_NDARRAY_ELEMENTS // max(int(capacity), 1)", "    fit = 2**40 // max(int(capacity), 1)",
      ["tests/test_grid.py", "tests/test_solver.py"], "neighbour lists of 50 M particles past Taichi's 32-bit index"),
    M("checkpoint-live-from-another-array", "diffuse/driver.py",
      '    return {"positions": last.positions, "velocities": last.velocities,',
      '    return {"positions": last.velocities, "velocities": last.velocities,',
      ["tests/test_diffuse.py"], "a resume's live diffuse particles read back from the wrong field of their file"),
    M("checkpoint-live-count-unchecked", "diffuse/driver.py",
      '    if len(last) != live or "lifetime" not in last.arrays or last.velocities is None or last.ids is None:',
      '    if False:',
      ["tests/test_diffuse.py"], "a resume takes another frame's diffuse particles from a changed file"),
    M("checkpoint-live-lost-with-a-pass", "diffuse/driver.py",
      "        _keep_live_in_checkpoint(out, {rel for _, rel in old})\n", "        pass\n",
      ["tests/test_diffuse.py"], "a foam pass removes the diffuse file simulate's checkpoint takes its particles from"),
    M("checkpoint-live-file-outside-the-run", "diffuse/driver.py",
      "    if problem is not None:\n        raise InputError(f\"{out / CHECKPOINT}",
      "    if False:\n        raise InputError(f\"{out / CHECKPOINT}",
      ["tests/test_diffuse.py"], "a resume reads the live particles from a file outside the run its checkpoint names"),
    M("readback-waited-before-the-next-frame", "diffuse/generator.py",
      "        if self._pending_reads_live:\n", "        if True:\n",
      ["tests/test_background_writer.py"], "the next frame's kernels wait for the last frame's records to come back"),
    M("records-packed-over-their-copy", "diffuse/generator.py",
      "            self.settle()  # array is packed again below", "            pass  # array is packed again below",
      ["tests/test_background_writer.py"], "a frame's records packed into the array the last frame's copy reads"),
    M("history-old-layout-taken-as-new", "diffuse/budget.py",
      "    if rows.ndim == 3 and rows.shape[1:] == (HISTORY_SAMPLE, 5):",
      "    if False:",
      ["tests/test_budget.py"], "a checkpoint's history in the layout before 2026-11-28 read as the new one"),
    M("history-columns-of-other-rows", "diffuse/budget.py",
      "    rows[:, -1, k * per:(k + 1) * per] = np.asarray(frame_sample(per)).T",
      "    rows[:, 0, k * per:(k + 1) * per] = np.asarray(frame_sample(per)).T",
      ["tests/test_budget.py"], "a frame's history sample written into the first row, not the last"),
    M("blender-session-dir-left", "workers.py",
      "    remove_blender_session_dir()\n    os._exit(code)", "    os._exit(code)",
      ["tests/test_errors.py"], "a Blender worker leaves its temporary folder behind (os._exit skips bpy's teardown)"),
    M("blender-session-dir-any-name", "workers.py",
      "        if (BLENDER_SESSION_DIR.fullmatch(os.path.basename(path)) and path not in _temp_bases(bpy)",
      "        if (path not in _temp_bases(bpy)",
      ["tests/test_errors.py"], "a worker removes whatever folder bpy.app.tempdir names, a user's included"),
    M("blender-session-dir-base-too", "workers.py",
      " and path not in _temp_bases(bpy)\n", "\n",
      ["tests/test_errors.py"], "a worker removes the base folder Blender fell back to (a user's TMPDIR)"),
    M("birth-sums-run-short", "diffuse/kernels.py",
      "for i in range(t * BIRTH_RUN, ti.min(n, (t + 1) * BIRTH_RUN)):",
      "for i in range(t * BIRTH_RUN, ti.min(n, (t + 1) * BIRTH_RUN - 1)):",
      ["tests/test_diffuse_generate.py"], "birth_sums leaves the last particle of each thread's run out"),
    M("speed-squared-other-order", "diffuse/generator.py",
      "    return x * x + y * y + z * z", "    return z * z + y * y + x * x",
      ["tests/test_diffuse_generate.py"], "|v|² summed in another order than einsum's: other bits, other flags"),
    M("foam-pass-no-finite-check", "diffuse/driver.py",
      "            raise InputError(f\"{path}: missing array 'velocity'\")\n        fr.check_finite()\n",
      "            raise InputError(f\"{path}: missing array 'velocity'\")\n",
      ["tests/test_errors.py"], "a foam pass takes a frame with an infinite velocity without a word"),
]


# ---------------------------------------------------------------------------- machinery
def _git_tree(rev: str, paths: list[str], dest: Path) -> None:
    """Extract ``paths`` of commit ``rev`` into ``dest``."""
    data = subprocess.run(["git", "-C", str(ROOT), "archive", "--format=tar", rev, *paths],
                          check=True, capture_output=True).stdout
    with tarfile.open(fileobj=io.BytesIO(data)) as t:
        t.extractall(dest, filter="data")


IGNORE = shutil.ignore_patterns(".git", ".venv", "out", "__pycache__", ".pytest_cache", "*.egg-info", "view_out")


def make_copy(base: Path, src_rev: str | None, tests_rev: str | None, overlay: list[str] = ()) -> Path:
    """A copy of the repository at base/main (base/shared links to the data beside the clone);
    ``overlay``: paths copied from the working tree over it (new test files on an old commit)."""
    tree = base / "main"
    if src_rev:
        tree.mkdir(parents=True)
        _git_tree(src_rev, ["."], tree)
    else:
        shutil.copytree(ROOT, tree, ignore=IGNORE, symlinks=True)
    if tests_rev:
        shutil.rmtree(tree / "tests")
        _git_tree(tests_rev, ["tests"], tree)
    for rel in overlay:
        src, dst = ROOT / rel, tree / rel
        if src.is_dir():
            shutil.copytree(src, dst, ignore=IGNORE, dirs_exist_ok=True)
        else:
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dst)
    shared = ROOT.parent / "shared"
    if shared.is_dir():
        (base / "shared").symlink_to(shared)
    return tree


def apply(tree: Path, m: Mutation) -> str | None:
    """Apply ``m`` in the copy; returns the original text, or None when the snippet is not there exactly once."""
    path = tree / "src" / "whitecap" / m.file
    if not path.is_file():
        return None
    text = path.read_text()
    if text.count(m.old) != 1:
        return None
    path.write_text(text.replace(m.old, m.new))
    return text


def run_tests(tree: Path, tests: list[str], timeout: float) -> tuple[str, float, str]:
    """(status, seconds, output) of ``pytest -x -q`` on ``tests`` in the copy."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(tree / "src") + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env["PYTHONDONTWRITEBYTECODE"] = "1"  # a mutated module must never be served from a stale .pyc
    env.setdefault("WHITECAP_PROGRESS", "0")
    cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", "--no-header", "-rfE", *tests]
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, cwd=tree, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, start_new_session=True)
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, _ = proc.communicate()
        return "TIMEOUT", time.monotonic() - t0, out
    dt = time.monotonic() - t0
    status = {0: "SURVIVED", 1: "CAUGHT"}.get(proc.returncode, "ERROR")
    return status, dt, out


def first_failure(out: str) -> str:
    for pat in (r"^FAILED (\S+)", r"^ERROR (\S+)", r"^(\S+::\S+) FAILED"):
        m = re.search(pat, out, re.M)
        if m:
            return m.group(1)
    m = re.search(r"^_+ (\S.*?) _+$", out, re.M)
    return m.group(1) if m else ""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--list", action="store_true", help="list the mutations and exit")
    ap.add_argument("--only", action="append", default=[], help="run only this mutation (repeatable; comma lists too)")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds per mutation (default 900)")
    ap.add_argument("--src-rev", help="audit the source of this git revision instead of the working tree")
    ap.add_argument("--tests-rev", help="use tests/ of this git revision (e.g. a baseline before new tests)")
    ap.add_argument("--overlay", action="append", default=[],
                    help="copy this path from the working tree over the copy (repeatable), e.g. a new test file")
    ap.add_argument("--check", action="store_true", help="first run every covering test file on the unmutated copy")
    ap.add_argument("--json", type=Path, help="write the results here")
    ap.add_argument("--logs", type=Path, help="keep each mutation's pytest output in this directory")
    ap.add_argument("--keep", action="store_true", help="keep the temporary copy")
    a = ap.parse_args(argv)

    only = {n for o in a.only for n in o.split(",") if n}
    unknown = only - {m.name for m in MUTATIONS}
    if unknown:
        print(f"unknown mutation(s): {', '.join(sorted(unknown))} (see --list)", file=sys.stderr)
        return 2
    todo = [m for m in MUTATIONS if not only or m.name in only]
    if a.list:
        for m in todo:
            print(f"{m.name:42s} {m.file:24s} {', '.join(t.removeprefix('tests/') for t in m.tests)}")
            if m.what:
                print(f"{'':42s} {m.what}")
        print(f"{len(todo)} mutations")
        return 0

    base = Path(tempfile.mkdtemp(prefix="whitecap_mutation_"))
    tree = make_copy(base, a.src_rev, a.tests_rev, a.overlay)
    if a.logs:
        a.logs.mkdir(parents=True, exist_ok=True)
    print(f"copy: {tree}  (src: {a.src_rev or 'working tree'}, tests: {a.tests_rev or 'working tree'}"
          + (f", overlay: {' '.join(a.overlay)}" if a.overlay else "") + ")", flush=True)
    results = []
    try:
        if a.check:
            files = sorted({t.split("::")[0] for m in todo for t in m.tests if (tree / t.split("::")[0]).exists()})
            status, dt, out = run_tests(tree, files, a.timeout * 4)
            print(f"unmutated: {'pass' if status == 'SURVIVED' else status} ({dt:.0f} s)", flush=True)
            if status != "SURVIVED":
                print(out[-3000:])
                print("the unmutated tests must pass before the audit means anything", file=sys.stderr)
                return 1
        for k, m in enumerate(todo, 1):
            tests = [t for t in m.tests if (tree / t.split("::")[0]).exists()]
            original = apply(tree, m)
            if original is None:
                status, dt, out, where = "STALE", 0.0, "", f"snippet not found once in {m.file}"
            elif not tests:
                (tree / "src" / "whitecap" / m.file).write_text(original)
                status, dt, out, where = "SURVIVED", 0.0, "", "no covering test file"
            else:
                try:
                    status, dt, out = run_tests(tree, tests, a.timeout)
                finally:
                    (tree / "src" / "whitecap" / m.file).write_text(original)
                where = first_failure(out) if status == "CAUGHT" else ""
            if a.logs and out:
                (a.logs / f"{m.name}.log").write_text(out)
            results.append({"name": m.name, "file": m.file, "status": status, "seconds": round(dt, 1),
                            "caught_by": where, "tests": tests, "what": m.what})
            print(f"[{k:2d}/{len(todo)}] {status:8s} {m.name:42s} {dt:6.0f} s  {where}", flush=True)
    finally:
        if not a.keep:
            shutil.rmtree(base, ignore_errors=True)

    applied = [r for r in results if r["status"] != "STALE"]
    caught = [r for r in applied if r["status"] == "CAUGHT"]
    print()
    for label in ("SURVIVED", "TIMEOUT", "ERROR", "STALE"):
        rows = [r for r in results if r["status"] == label]
        if rows:
            print(f"{label.lower()}:")
            for r in rows:
                print(f"  {r['name']:42s} {r['file']:24s} {r['what'] or r['caught_by']}")
    rate = 100.0 * len(caught) / len(applied) if applied else 0.0
    print(f"\ncaught {len(caught)} of {len(applied)} mutations ({rate:.0f} %)")
    if a.json:
        a.json.write_text(json.dumps({"caught": len(caught), "applied": len(applied), "rate": rate,
                                      "src_rev": a.src_rev, "tests_rev": a.tests_rev, "results": results}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
