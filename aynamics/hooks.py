"""Per-step forces a MuJoCo Batch cannot hold: Magnus lift and speed-dependent friction (`physics.magnus`,
`physics.friction_slope`, the scene language's extension fields), recomputed from the state before each physics
step. `aynamics.simulate` steps a batch through `step_hooked` when a scene sets either; the audit's candidates
(`aynamics.effects`) do the same.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from mujoco import batch as mjbatch

from aynamics.mujoco_model import Template, pair_sliding, quat_to_mat
from aynamics.scene import Scene


@dataclass(frozen=True)
class Hooks:
    """Per-step forces a Batch cannot hold: Magnus lift and speed-dependent friction, (n, N) per object."""

    template: Template
    magnus: np.ndarray  # (n, N) k, kg
    slope: np.ndarray  # (n, N) κ, s/m
    mass: np.ndarray  # (n, N) kg

    @staticmethod
    def of(scenes: list[Scene], tpl: Template) -> Hooks | None:
        """The scenes' hook coefficients, or None when no object has magnus or friction_slope set."""
        magnus = np.array([[o.physics.magnus or 0.0 for o in s.objects] for s in scenes], dtype=float)
        slope = np.array([[o.physics.friction_slope or 0.0 for o in s.objects] for s in scenes], dtype=float)
        if not magnus.any() and not slope.any():
            return None
        mass = np.array([[float(o.physics.mass) for o in s.objects] for s in scenes], dtype=float)
        return Hooks(tpl, magnus, slope, mass)


def magnus_force(k: np.ndarray, spin: np.ndarray, v: np.ndarray, mass: np.ndarray, h: np.ndarray) -> np.ndarray:
    """(n, 3) the force that turns v as Magnus lift k·ω×v does over one step of h seconds, without changing its
    length: m (v' − v) / h with v' = Cayley(h·a) v, a = k·ω / m, that is
    (k·ω×v + (h/2)·a×(k·ω×v)) / (1 + (h|a|/2)²). k·ω×v itself, applied for a step, lengthens v by a factor
    √(1 + (h|a|)²) a step: a ball of 0.1 kg at k = 0.05, spinning at 40 rad/s with no gravity, went from 3 to 6.9 m/s
    in 1 s (its path a circle at 3 m/s). k (n,), spin and v (n, 3) in world axes, mass and h (n,)."""
    kw = k[:, None] * spin
    a = kw / mass[:, None]
    lift = np.cross(kw, v)
    half = 0.5 * h[:, None]
    return (lift + half * np.cross(a, lift)) / (1.0 + (half * np.linalg.norm(a, axis=1, keepdims=True)) ** 2)


def step_hooked(b: mjbatch.Batch, hooks: Hooks, nstep: int, record: tuple[str, ...]) -> dict[str, np.ndarray]:
    """`Batch.rollout` with the hook forces recomputed from the state before each physics step.

    Before step k: xfrc_applied = Magnus lift k·ω×v (world) on each object body, as a turn of v that keeps its
    length (`magnus_force`), and the object geom's sliding friction
    max(μ + κ·|v_xy|, 0), written into its contact pairs as `write_pairs` does (the floor's: the object's μ; two
    objects': the larger).
    Returns the recorded fields after every step, (n, nstep, ...) as `Batch.rollout` does.
    """
    tpl = hooks.template
    qpos, qvel = b.bind("qpos"), b.bind("qvel")
    xfrc = b.bind("xfrc_applied")  # (n, nbody, 6): world force, torque
    fric = b.expand("geom_friction")  # (n, ngeom, 3)
    mu0 = fric[:, tpl.geom_ids, 0].copy()  # (n, N)
    pfric = b.expand("pair_friction")  # (n, npair, 5): the contacts' friction (every contact is a pair)
    pmu0 = pfric[:, tpl.contact_pairs, :2].copy()
    live = {name: b.bind(name) for name in record}
    out = {name: np.empty((b.nsim, nstep, *np.shape(v)[1:])) for name, v in live.items()}
    magnus, sliding = hooks.magnus.any(), hooks.slope.any()
    h = b.expand("opt.timestep").reshape(b.nsim).copy() if magnus else None  # (n,) each scene's physics step
    try:
        for step in range(nstep):
            for i, (a, d) in enumerate(zip(tpl.qpos_adr, tpl.dof_adr, strict=True)):
                v = qvel[:, d : d + 3]  # (n, 3) world linear velocity
                if magnus:
                    spin = np.einsum("nij,nj->ni", quat_to_mat(_unit(qpos[:, a + 3 : a + 7])), qvel[:, d + 3 : d + 6])
                    xfrc[:, tpl.body_ids[i], :3] = magnus_force(hooks.magnus[:, i], spin, v, hooks.mass[:, i], h)
                if sliding:
                    speed = np.linalg.norm(v[:, :2], axis=1)
                    fric[:, tpl.geom_ids[i], 0] = np.maximum(mu0[:, i] + hooks.slope[:, i] * speed, 0.0)
            if sliding:
                pfric[:, tpl.contact_pairs, :2] = pair_sliding(tpl, fric[:, tpl.geom_ids, 0])[..., None]
            b.step()
            for name, v in live.items():
                out[name][:, step] = v
    finally:
        fric[:, tpl.geom_ids, 0] = mu0
        pfric[:, tpl.contact_pairs, :2] = pmu0
        xfrc[...] = 0.0
    return out


def _unit(q: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore", divide="ignore"):
        return q / np.linalg.norm(q, axis=-1, keepdims=True)
