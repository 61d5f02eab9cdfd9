"""Initial configurations: where the objects stand and where the TCP starts.

Parameterised as in the paper: the TCP starts at ``(r, theta, phi)`` from the adversarial
object's centre (``phi`` = polar angle from its up axis, ``theta`` = azimuth), aimed near the scene
with noise. Every configuration is a pure function of ``(spec, seed)``, so pools on disk only
need the seeds to be reproduced; they store the resolved values too, for inspection and so a
changed spec is detected rather than silently reinterpreted.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from sim.assets import BUILTIN_MESHES, build_mesh
from sim.errors import AdvobjError
from sim.geometry import look_at, make_T, rot_z

__all__ = [
    "InitialConfig",
    "PoolError",
    "sample_config",
    "sample_pool",
    "save_pool",
    "load_pool",
    "object_local_centers",
    "spec_fingerprint",
    "object_poses_world",
    "PARTS",
    "config_part",
    "config_id",
    "pose_id",
    "copy_pool",
    "in_part",
    "part_seeds",
]

_MAX_TRIES = 200

# The held-out split. Every configuration seed belongs to exactly one part, by a hash of the seed
# alone: the attack draws its EOT configurations from "attack" and picks its best texture on
# "validation"; evaluations use only "evaluation". The split depends on nothing a run can choose
# (no run seed, no pool file), so two runs can never disagree about it and a texture is never
# scored on a configuration it was optimised or selected on. Shares: 40% / 10% / 50%.
PARTS = ("attack", "validation", "evaluation")
_PART_BOUNDS = (0.4, 0.5)  # cumulative shares of attack, then validation; the rest is evaluation
_SPLIT_SALT = b"advobj-config-split/1:"


class PoolError(AdvobjError, ValueError):
    """A config pool file is missing, malformed, or was made for a different scene."""


@dataclass(frozen=True)
class InitialConfig:
    """One episode start. ``object_xy_yaw: (K, 3)`` = (x m, y m, yaw rad) per spec object."""

    seed: int
    object_xy_yaw: tuple[tuple[float, float, float], ...]
    r_m: float
    theta_rad: float
    phi_rad: float
    T_world_tcp: tuple[tuple[float, ...], ...]

    @property
    def T_world_tcp_array(self) -> np.ndarray:
        return np.asarray(self.T_world_tcp, dtype=np.float64)

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> "InitialConfig":
        return InitialConfig(
            seed=int(d["seed"]),
            object_xy_yaw=tuple(tuple(float(v) for v in row) for row in d["object_xy_yaw"]),
            r_m=float(d["r_m"]),
            theta_rad=float(d["theta_rad"]),
            phi_rad=float(d["phi_rad"]),
            T_world_tcp=tuple(tuple(float(v) for v in row) for row in d["T_world_tcp"]),
        )


def config_part(seed: int) -> str:
    """The part (``"attack"``, ``"validation"`` or ``"evaluation"``) that configuration ``seed`` belongs to."""
    h = hashlib.sha256(_SPLIT_SALT + str(int(seed)).encode()).digest()
    u = int.from_bytes(h[:8], "big") / 2.0**64
    return PARTS[0] if u < _PART_BOUNDS[0] else (PARTS[1] if u < _PART_BOUNDS[1] else PARTS[2])


def in_part(configs, part: str) -> list:
    """The configurations of ``configs`` whose seed lies in ``part`` (order kept)."""
    if part not in PARTS:
        raise ValueError(f"part: unknown part {part!r}; choose one of {PARTS}")
    return [c for c in configs if config_part(c.seed) == part]


def part_seeds(part: str, start: int = 0):
    """Seeds ``>= start`` of ``part``, in increasing order (an endless generator)."""
    if part not in PARTS:
        raise ValueError(f"part: unknown part {part!r}; choose one of {PARTS}")
    s = max(0, int(start))
    while True:
        if config_part(s) == part:
            yield s
        s += 1


def config_id(config: "InitialConfig") -> str:
    """Content hash of one configuration (seed and every resolved value): the identity used to
    prove that an evaluation and an attack share no configuration, whatever files they came from."""
    payload = json.dumps(config.to_dict(), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(payload.encode()).hexdigest()[:20]


def pose_id(config: "InitialConfig") -> str:
    """Content hash of one configuration's poses, without its seed: the object placements, the
    start pose and its polar coordinates, rounded to 1e-9 (nm, nrad). Two configurations drawn
    from different seeds that put everything in the same place share it, so an overlap check on it
    can find what a check on :func:`config_id` (which includes the seed) cannot."""
    d = config.to_dict()
    d.pop("seed")

    def rounded(v):
        return [rounded(x) for x in v] if isinstance(v, (list, tuple)) else round(float(v), 9) + 0.0

    payload = json.dumps({k: rounded(v) for k, v in d.items()}, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(payload.encode()).hexdigest()[:20]


def object_poses_world(object_xy_yaw) -> np.ndarray:
    """``T_world_object: (K, 4, 4)`` from ``(K, 3)`` table placements (x, y, yaw)."""
    a = np.asarray(object_xy_yaw, dtype=np.float64).reshape(-1, 3)
    t = np.concatenate([a[:, :2], np.zeros((len(a), 1))], -1)
    return make_T(rot_z(a[:, 2]), t)


@lru_cache(maxsize=64)
def _mesh_center(
    mesh: str, scale, units: str = "m", up_axis: str | None = None, placement: str = "auto"
) -> tuple[float, float, float]:
    m = build_mesh(mesh, scale, units, up_axis, placement)
    lo, hi = m.bounds
    return tuple(float(v) for v in (lo + hi) / 2.0)


def object_local_centers(spec) -> np.ndarray:
    """Bounding-box centres ``(K, 3)`` m of the spec's objects in their own frames."""
    return np.array([_mesh_center(o.mesh, o.scale, o.units, o.up_axis, o.placement) for o in spec.objects])


def _place_objects(spec, rng: np.random.Generator) -> np.ndarray:
    init = spec.init
    nominal = np.array([[o.pose.x_m, o.pose.y_m, math.radians(o.pose.yaw_deg)] for o in spec.objects])
    if not init.randomize_objects:
        return nominal
    for _ in range(_MAX_TRIES):
        xy = np.stack(
            [rng.uniform(*init.region_x_m, size=len(nominal)), rng.uniform(*init.region_y_m, size=len(nominal))], -1
        )
        d = np.linalg.norm(xy[:, None] - xy[None], axis=-1) + np.eye(len(xy)) * 1e9
        if d.min() >= init.min_separation_m:
            yaw = rng.uniform(-math.pi, math.pi, size=len(nominal))
            return np.concatenate([xy, yaw[:, None]], -1)
    raise ValueError(
        f"init: cannot place {len(nominal)} objects {init.min_separation_m} m apart in region "
        f"x={init.region_x_m}, y={init.region_y_m}; enlarge the region or lower min_separation_m"
    )


def sample_config(spec, seed: int, centers_local: np.ndarray | None = None) -> InitialConfig:
    """The initial configuration for ``seed`` (deterministic).

    Rejects starts where the TCP is below ``min_tcp_height_m + 0.04`` or within 1.5 success radii
    of an object (an episode that is over before it starts), re-drawing from the same stream.
    """
    init = spec.init
    centers_local = object_local_centers(spec) if centers_local is None else centers_local
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xADB0]))
    adv, goal = spec.object_index("adversarial"), spec.object_index("goal")
    for _ in range(_MAX_TRIES):
        placement = _place_objects(spec, rng)
        T_objs = object_poses_world(placement)
        centers = np.einsum("kij,kj->ki", T_objs[:, :3, :3], centers_local) + T_objs[:, :3, 3]
        r = rng.uniform(*init.r_range_m)
        phi = math.radians(rng.uniform(*init.phi_range_deg))
        theta = math.radians(rng.uniform(*init.theta_range_deg))
        direction = np.array([math.sin(phi) * math.cos(theta), math.sin(phi) * math.sin(theta), math.cos(phi)])
        p_tcp = centers[adv] + r * direction
        if p_tcp[2] < spec.episode.min_tcp_height_m + 0.04:
            continue
        if np.linalg.norm(centers - p_tcp, axis=-1).min() < 1.5 * spec.episode.success_radius_m:
            continue
        aim = 0.5 * (centers[adv] + centers[goal]) + rng.normal(0.0, init.aim_noise_m, size=3)
        if np.linalg.norm(aim - p_tcp) < 1e-3:
            continue
        T = look_at(p_tcp, aim)  # TCP +z toward the aim point, image-down as close to world-down
        return InitialConfig(
            seed=int(seed),
            object_xy_yaw=tuple(tuple(float(v) for v in row) for row in placement),
            r_m=float(r),
            theta_rad=float(theta),
            phi_rad=float(phi),
            T_world_tcp=tuple(tuple(float(v) for v in row) for row in T),
        )
    raise ValueError(f"seed {seed}: no valid initial configuration after {_MAX_TRIES} draws; check spec.init")


def sample_pool(spec, n: int, seed: int = 0, part: str | None = None) -> list[InitialConfig]:
    """``n`` configurations with seeds ``seed, seed + 1, ...`` (only seeds of ``part`` if given)."""
    centers = object_local_centers(spec)
    if part is None:
        return [sample_config(spec, seed + i, centers) for i in range(n)]
    seeds = part_seeds(part, seed)
    return [sample_config(spec, next(seeds), centers) for _ in range(n)]


# Object fields added after pools were first written, with the defaults that change nothing. On
# a built-in mesh they never matter, so they are left out of its fingerprint there: every pool a
# user already has stays valid. On a mesh file they shape the object, so they always count.
_LATER_OBJECT_DEFAULTS = {"units": "m", "up_axis": None, "placement": "auto", "attack_region": None}


def _object_payload(o) -> dict:
    d = o.model_dump()
    if d.get("mesh") in BUILTIN_MESHES:
        for k, v in _LATER_OBJECT_DEFAULTS.items():
            if d.get(k, v) == v:
                d.pop(k, None)
    return d


def spec_fingerprint(spec) -> str:
    """Short hash of everything in the spec that affects configurations."""
    payload = json.dumps(
        {
            "objects": [_object_payload(o) for o in spec.objects],
            "init": spec.init.model_dump(),
            "episode": spec.episode.model_dump(),
        },
        sort_keys=True,
        default=str,
    )
    return hashlib.sha256(payload.encode()).hexdigest()[:16]


def save_pool(path: str | Path, spec, configs: list[InitialConfig], meta: dict | None = None) -> Path:
    """Write a pool as JSON (atomically: a crash never leaves a half-written file)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = {
        "format": "advobj-config-pool/1",
        "spec_fingerprint": spec_fingerprint(spec),
        "meta": meta or {},
        "configs": [c.to_dict() for c in configs],
    }
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(doc))
    tmp.replace(path)
    return path


def copy_pool(src: str | Path, dst: str | Path, meta=None) -> Path:
    """Copy a pool file to ``dst`` as it is, its ``meta`` passed through ``meta(dict) -> dict`` when
    given (e.g. to drop machine paths before it is committed)."""
    doc = json.loads(Path(src).read_text(encoding="utf-8"))
    if meta is not None:
        doc["meta"] = meta(dict(doc.get("meta") or {}))
    dst = Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_name(dst.name + ".tmp")
    tmp.write_text(json.dumps(doc), encoding="utf-8")
    tmp.replace(dst)
    return dst


def load_pool(path: str | Path, spec=None) -> list[InitialConfig]:
    """Read a pool; with ``spec``, refuse a pool made for a different scene."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except IsADirectoryError:
        raise PoolError(f"{path}: is a directory, expected a config pool JSON file") from None
    except OSError as err:
        raise PoolError(f"{path}: cannot read config pool ({err.strerror})") from None
    except UnicodeDecodeError as err:
        raise PoolError(
            f"{path}: not a JSON config pool: not UTF-8 text (byte {err.start}), is it a binary file?"
        ) from None
    except RecursionError:
        raise PoolError(f"{path}: not a usable JSON config pool: nested too deeply") from None
    except json.JSONDecodeError as err:
        raise PoolError(f"{path}: not a JSON config pool ({err})") from None
    if not isinstance(doc, dict) or doc.get("format") != "advobj-config-pool/1":
        raise PoolError(f"{path}: not an advobj config pool (missing format 'advobj-config-pool/1')")
    if spec is not None and doc.get("spec_fingerprint") != spec_fingerprint(spec):
        raise PoolError(f"{path}: pool was made for a different scene (spec_fingerprint mismatch)")
    try:
        return [InitialConfig.from_dict(c) for c in doc["configs"]]
    except (KeyError, TypeError, ValueError) as err:
        raise PoolError(f"{path}: malformed config entry ({err})") from None
