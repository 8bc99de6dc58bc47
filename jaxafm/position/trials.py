"""Positioning trials: from where a stage's survey left things, the move to each target, and
for A+B+C the local scan on it, the move to the centre it found and the push (paper sections
III-B, III-C and IV). Every target is an independent trial (``vmap``); the results are typed
(:class:`TrialResults`)."""

from __future__ import annotations

from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax

from ..instrument.samples import Indented, Particles
from .online import NO_PUSH_FIELD, PushField
from .positioning import LocalScan, Positioner, Push, PushCheck, ScanResult, goto, local_scan, push_and_check

#: particles each trial's local scan sees (the others lie beyond its lines)
NEARBY = 8
#: a trial keeps every PUSH_PATH_STRIDE-th sample of the first push's path
PUSH_PATH_STRIDE = 8


def nearby(sample: Indented, centre: jax.Array) -> Particles:
    """The :data:`NEARBY` particles of ``sample`` nearest ``centre``: what a trial's moves, local
    scan and push see, imaged in closed form. The indents are left out: a simplification,
    as the particles lie about a quarter of a landmark cell or more from the nearest one."""
    parts = sample.base
    k = min(NEARBY, parts.radii.shape[0])
    idx = lax.top_k(-jnp.sum((parts.centres - centre) ** 2, axis=-1), k)[1]
    return Particles(parts.centres[idx], parts.radii[idx], parts.substrate)


class StepC(eqx.Module):
    """Step C of a trial: the local ``scan``, the true ``tip`` (2,) nm after the move to the
    centre it found, and that tip's distance from the particle's true centre ``error_nm``."""

    scan: ScanResult
    tip: jax.Array
    error_nm: jax.Array


class TrialResults(eqx.Module):
    """Every trial's results (leading axis: trials): the true ``tip`` (2,) nm after the move to
    the target and its distance from the particle's true centre ``error_nm``; with step C,
    ``step_c``; with the push, ``push`` (the first push's path kept at every
    :data:`PUSH_PATH_STRIDE`-th sample) and ``push_goal`` (2,) nm, the particle's true centre
    moved by the wanted distance and direction."""

    tip: jax.Array
    error_nm: jax.Array
    step_c: Optional[StepC] = None
    push: Optional[PushCheck] = None
    push_goal: Optional[jax.Array] = None


@eqx.filter_jit
def trials(
    pos: Positioner,
    seen: Particles,
    stand,
    targets,
    truth,
    radii,
    directions,
    distances,
    keys,
    local: Optional[LocalScan] = None,
    push_spec: Optional[Push] = None,
    approach: float = 0.0,
    learnt: PushField = NO_PUSH_FIELD,
    odds=None,
) -> TrialResults:
    """Go to every target (K, 2) nm from ``stand``, one independent trial each (``vmap``), with
    ``seen`` (batched over the trials) the particles each trial's tip meets; with ``local``,
    then step C, and with ``push_spec`` the push of each particle by ``distances`` (K,) nm along
    the unit ``directions`` (K, 2). The move to the target makes ``approach``
    (:func:`~jaxafm.position.positioning.goto`); every push is commanded through ``learnt``
    (:func:`~jaxafm.position.positioning.push_and_check`), a push whose predicted success ``odds``
    (K,) is below ``push_spec.min_odds`` withheld (``None``: every push is made). Errors against
    the true centres ``truth`` (K, 2) nm of particles of ``radii`` (K,) nm; trial k draws from
    ``keys[k]``."""
    odds = jnp.ones(targets.shape[0]) if odds is None else jnp.asarray(odds, dtype=float)

    def one(near, target, p, R, d, dist, key, chance):
        k = jax.random.split(key, 4)
        xy, _, s = goto(pos, near, stand, target, k[0], approach=approach)
        error = jnp.linalg.norm(xy - p)
        if local is None:
            return TrialResults(xy, error)
        res, s = local_scan(pos, near, s, target, R, k[1], local)
        xy_c, _, s = goto(pos, near, s, res.centre, k[2])
        step_c = StepC(res, xy_c, jnp.linalg.norm(xy_c - p))
        if push_spec is None:
            return TrialResults(xy, error, step_c)
        checked, s = push_and_check(
            pos,
            near,
            s,
            res.centre,
            p,
            R,
            d,
            dist,
            k[3],
            push_spec,
            local,
            approach,
            stand.wanted,
            learnt,
            chance,
        )
        checked = eqx.tree_at(lambda c: c.first.path, checked, checked.first.path[::PUSH_PATH_STRIDE])
        return TrialResults(xy, error, step_c, checked, p + dist * d)

    return jax.vmap(one)(seen, targets, truth, radii, directions, distances, keys, odds)
