"""The competence gate: a policy that cannot do the task is refused before it is attacked or evaluated.

An attack or an evaluation of a policy that rarely reaches the goal says nothing: its task-feasible
pool (:mod:`sim.policies.pool`) is a handful of configurations found by minutes of clean rollouts,
and every rate over it is a rate over a tiny n. The gate takes the policy's clean success on the
scene (the fraction of clean episodes that reach the goal):

* from its card (:class:`sim.policies.card.CleanSuccess`, the final clean evaluation of ``advobj
  policy train``) when the card was made on this scene (the same
  :func:`sim.configs.spec_fingerprint`: objects, init region, episode length): no rollout;
* otherwise, when the caller is about to roll the policy out to find task-feasible configurations
  (``measure``), measured on at most :data:`CHECK_EPISODES` clean episodes of the scene,
  :data:`CHECK_ROUND` at a time, by :func:`sim.policies.pool.build_feasible` (the evaluation's
  clean-arm rollout: an episode counts when the policy reaches the goal). It stops as soon as the
  outcome is decided (:func:`decide`).

Below ``min_clean_success`` (default :data:`DEFAULT_MIN_CLEAN_SUCCESS`; 0 turns the gate off)
:func:`require_competence` raises :class:`IncompetentPolicyError`: one line with the figure, n,
the threshold and what to do. Importing this module loads no numpy or torch: the commands take
their option's default from here.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Literal

from tqdm import tqdm

from sim.errors import AdvobjError
from sim.stats import Proportion, proportion, wilson_interval

__all__ = [
    "DEFAULT_MIN_CLEAN_SUCCESS",
    "CHECK_EPISODES",
    "CHECK_ROUND",
    "FLAG",
    "CompetenceError",
    "IncompetentPolicyError",
    "CleanSuccessFigure",
    "card_clean_success",
    "decide",
    "measure_clean_success",
    "require_competence",
]

DEFAULT_MIN_CLEAN_SUCCESS = 0.5
# At most 16 clean episodes, 8 at a time. After the first 8 at the default threshold, 0-1 successes
# refuse (Wilson 95% upper bound 32% / 47%) and 7-8 pass (lower bound 53% / 68%); the rest take 8 more.
CHECK_EPISODES = 16
CHECK_ROUND = 8
FLAG = "--min-clean-success"


class CompetenceError(AdvobjError, ValueError):
    """A competence threshold that is not a fraction in [0, 1]."""


class IncompetentPolicyError(CompetenceError):
    """The policy's clean success on the scene is below the threshold; :attr:`figure` holds it."""

    def __init__(self, message: str, figure: "CleanSuccessFigure"):
        super().__init__(message)
        self.figure = figure


@dataclass(frozen=True)
class CleanSuccessFigure:
    """A policy's clean success on a scene and where it comes from (its card, or measured now)."""

    success: Proportion
    source: Literal["card", "measured"]

    def describe(self) -> str:
        """``6.2% (1/16 episodes, from its card)``, or with the interval when measured now."""
        s = self.success
        if self.source == "card":
            return f"{100 * s.rate:.1f}% ({s.k}/{s.n} episodes, from its card)"
        pct = int(round(100 * s.confidence))
        return (
            f"{100 * s.rate:.1f}% ({s.k}/{s.n} clean episodes measured on this scene, {pct}% CI "
            f"{100 * s.lo:.1f}-{100 * s.hi:.1f}%)"
        )


def _threshold(value, flag: str) -> float:
    try:
        t = float(value)
    except (TypeError, ValueError):
        t = math.nan
    if not (0.0 <= t <= 1.0):  # NaN fails too
        raise CompetenceError(f"{flag}: expected a fraction of episodes in [0, 1] (0.5 = 50%), got {value!r}")
    return t


def card_clean_success(policy, spec) -> Proportion | None:
    """The clean success the policy's card records for ``spec`` (None: no card, no figure, or a
    figure made on another scene or episode length)."""
    from sim.configs import spec_fingerprint  # lazy: CLI start-up (numpy, trimesh)

    card = getattr(policy, "card", None)
    cs = getattr(card, "clean_success", None)
    if cs is None or cs.rate is None or not 0 < cs.n or not 0 <= cs.k <= cs.n:
        return None
    scene = (getattr(card, "training", None) or {}).get("scene")
    if not isinstance(scene, dict) or scene.get("fingerprint") != spec_fingerprint(spec):
        return None
    return proportion(cs.k, cs.n)


def decide(
    k: int, n: int, threshold: float, max_episodes: int = CHECK_EPISODES, confidence: float = 0.95
) -> Literal["pass", "refuse"] | None:
    """The gate's decision after ``k`` successes in ``n`` clean episodes (None: roll out more).

    Early, once the Wilson interval (``confidence``) lies wholly below ``threshold`` (refuse) or
    wholly at or above it (pass); at ``max_episodes``, the rate against ``threshold``. Either way a
    refusal has ``k / n < threshold`` and a pass ``k / n >= threshold``.
    """
    if max_episodes < 1:
        raise ValueError(f"max_episodes must be at least 1, got {max_episodes}")
    if n == 0:
        return None
    if n >= max_episodes:
        return "pass" if k / n >= threshold else "refuse"
    lo, hi = wilson_interval(k, n, confidence)
    if hi < threshold and k / n < threshold:
        return "refuse"
    if lo >= threshold and k / n >= threshold:
        return "pass"
    return None


def measure_clean_success(
    policy,
    spec,
    threshold: float,
    part: str = "evaluation",
    start_seed: int = 0,
    num_envs: int = CHECK_ROUND,
    max_episodes: int = CHECK_EPISODES,
    progress: bool = True,
) -> Proportion:
    """Clean success on ``spec`` over the configurations of ``part`` from ``start_seed`` on
    (:func:`sim.configs.part_seeds`), :data:`CHECK_ROUND` episodes a round, until :func:`decide`
    settles it against ``threshold`` (at most ``max_episodes``). Every candidate of a round is
    counted, feasible or not: the rate is unbiased whatever a pool already holds."""
    from sim.configs import part_seeds  # lazy: CLI start-up (numpy, trimesh)
    from sim.policies.pool import build_feasible  # lazy: CLI start-up (torch, pyrender)

    k = n = 0
    seeds = part_seeds(part, start_seed)
    bar = tqdm(total=max_episodes, desc="clean-success check", disable=not progress, dynamic_ncols=True)
    try:
        while decide(k, n, threshold, max_episodes) is None:
            m = min(CHECK_ROUND, max_episodes - n)
            batch = list(itertools.islice(seeds, m))
            # exactly these m candidates: the first m seeds of the part from batch[0] on
            got, tried = build_feasible(
                policy, spec, part, m, batch[0], min(num_envs, m), max_candidates=m, progress=False
            )
            k, n = k + len(got), n + tried
            bar.update(tried)
    finally:
        bar.close()
    return proportion(k, n)


def require_competence(
    policy,
    spec,
    min_clean_success: float = DEFAULT_MIN_CLEAN_SUCCESS,
    *,
    measure: bool = True,
    part: str = "evaluation",
    seed: int = 0,
    num_envs: int = CHECK_ROUND,
    progress: bool = True,
    name: str = "policy",
    flag: str = FLAG,
) -> CleanSuccessFigure | None:
    """The gate: the policy's clean success on ``spec`` from its card, else (with ``measure``)
    measured (:func:`measure_clean_success` on ``part`` from ``seed``); :class:`IncompetentPolicyError`
    below ``min_clean_success``. Returns the figure it went by (None: the gate is off, or there was
    no card figure and ``measure`` is False). ``name`` and ``flag`` name the policy and the option
    in the refusal."""
    t = _threshold(min_clean_success, flag)
    if t == 0.0:
        return None
    success = card_clean_success(policy, spec)
    if success is not None:
        figure = CleanSuccessFigure(success, "card")
    elif measure:
        figure = CleanSuccessFigure(
            measure_clean_success(policy, spec, t, part, seed, num_envs, progress=progress), "measured"
        )
    else:
        return None
    if figure.success.rate < t:
        raise IncompetentPolicyError(
            f"{name}: clean success {figure.describe()} is below {flag} {t:g}: it does not do the task in this "
            "scene, so an attack on it or an evaluation of it would mean nothing; train it longer, check that the "
            f"scene is the one it was trained for (objects, sizes, cameras), or lower {flag} (0 turns the check off)",
            figure,
        )
    return figure
