"""Learned policies: load a trained stable-baselines3 ``.zip`` or an exported ``.npz``.

Both artifacts carry the same metadata (``LearnedMeta``): the observation layout the policy
was trained on (version, M, k, size), the member configuration (ρ, τ, σ, ladder), the
control rate, the observation normalization (VecNormalize's running mean and variance,
when training used it) and the action scaling. The network works in a normalized action
space ``[-1, 1]^2``; ``act`` maps it to SI units ``[speed_mps, heading_change_rad]``
(DESIGN.md, Action), so a learned policy is a ``Policy`` like any classical one. Two
action modes (``compose_action``):

- absolute: the normalized action maps affinely onto ``[action_low, action_high]``;
- residual: a classical ``base`` policy (recorded in full with the learned one) proposes
  the action and the network adds ``a * residual_scale`` to it, clipped to
  ``[action_low, action_high]``. Learning a correction of a working controller is what
  makes a useful follower trainable in minutes on two cores; the base is part of the
  policy everywhere it runs (sim, deploy), so training and deployment compute the same.

- ``.npz``: written by ``openconvoy export``; the actor's layers as plain arrays and a numpy
  forward pass. Never imports torch, so vehicles deploy it without the training stack.
- ``.zip``: written by ``openconvoy train`` (SB3's own file with an ``openconvoy.json``
  member holding the metadata); loading it imports stable-baselines3 (and torch) lazily
  and takes the actor's layers out once, so it runs the ``.npz``'s numpy forward: a
  ``.zip`` and its export act, simulate and sweep alike to the bit.

A policy whose recorded layout differs from the convoy's (``layout=`` or
``member_config=`` given to the loader) is refused with a ValueError naming the difference.
"""

from __future__ import annotations

import json
import math
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from openconvoy.core.config import from_dict, to_dict
from openconvoy.core.errors import (
    DependencyMissing,
    InputFileError,
    MissingFileError,
    OpenConvoyError,
)
from openconvoy.core.member import MemberConfig
from openconvoy.core.observation import ObservationLayout
from openconvoy.core.policy import MAX_HEADING_CHANGE_RAD, make_action
from openconvoy.policies.classical import ClassicalConfig, ClassicalPolicy

META_MEMBER = "openconvoy.json"
"""Name of the metadata member inside a trained ``.zip``."""
NPZ_FORMAT = "openconvoy-learned-npz-1"
ACTIVATIONS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "tanh": np.tanh,
    "relu": lambda x: np.maximum(x, 0.0),
    "elu": lambda x: np.where(x > 0.0, x, np.expm1(np.minimum(x, 0.0))),
    "leaky_relu": lambda x: np.where(x > 0.0, x, 0.01 * x),
    "identity": lambda x: x,
}
"""Hidden-layer activations the numpy forward pass knows (SB3's usual ``activation_fn``s)."""
OUTPUTS = ("clip", "tanh")
"""How the network's last layer becomes a normalized action: ``clip`` to [-1, 1] (PPO's
Gaussian mean, as SB3's ``predict`` clips it) or ``tanh`` (SAC's squashed mean)."""


@dataclass(frozen=True)
class LearnedMeta:
    """What a learned policy records at training time.

    Attributes:
        algo: ``ppo`` or ``sac``.
        layout: ``ObservationLayout.describe()`` of the training observations.
        member_config: the member side the policy was trained with (its layout included).
        control_rate_hz: the rate it was trained at (Hz); deploy and sim tick at it.
        action_low, action_high: SI values of the normalized actions -1 and +1
            (``[speed_mps, heading_change_rad]``).
        obs_mean, obs_var: VecNormalize's observation statistics, or None (no normalization).
        obs_clip: normalized observations are clipped to ±obs_clip.
        obs_epsilon: added to the variance before the square root.
        name: a label for logs and reports.
        base: the classical policy a residual policy corrects (None: absolute actions).
        base_plugin: or the plug-in policy spec it corrects (``module:Name?k=v``,
            ``policies.plugin``; loaded by reference: it must be importable here).
        obs_features: an observation-features plug-in (``core.plugins.features``) whose
            ``feature_size`` numbers the network sees after the layout's (loaded by
            reference; a plug-in that now gives another count is refused).
        residual_scale: SI size of a full-scale (±1) residual, ``[m/s, rad]``.
        extra: free-form facts about the run (steps, seed).
    """

    algo: str
    layout: dict[str, int]
    member_config: MemberConfig
    control_rate_hz: float
    action_low: tuple[float, float]
    action_high: tuple[float, float]
    obs_mean: np.ndarray | None = None
    obs_var: np.ndarray | None = None
    obs_clip: float = 10.0
    obs_epsilon: float = 1e-8
    name: str = "learned"
    base: ClassicalConfig | None = None
    residual_scale: tuple[float, float] = (0.0, 0.0)
    extra: dict[str, Any] = field(default_factory=dict)
    base_plugin: str = ""
    obs_features: str = ""
    feature_size: int = 0

    def __post_init__(self) -> None:
        if self.base is not None and self.base_plugin:
            raise InputFileError("a residual policy has one base: classical or plug-in")
        if self.base is not None and self.base.member != self.member_config:
            raise InputFileError(
                "a residual policy's base must use the policy's member configuration"
            )
        if not (math.isfinite(self.control_rate_hz) and 0 < self.control_rate_hz <= 100):
            raise InputFileError(
                f"control_rate_hz: {self.control_rate_hz!r} is out of range; allowed: (0, 100] Hz"
            )
        size = int(self.layout["size"]) + self.feature_size
        for name, arr in (("obs_mean", self.obs_mean), ("obs_var", self.obs_var)):
            if arr is not None and np.shape(arr) != (size,):
                raise InputFileError(
                    f"{name} has shape {np.shape(arr)}, the layout has size {size}"
                )
        # The member config must describe the layout the policy records.
        self.member_config.layout.check_compatible(self.layout)

    def to_json(self) -> dict[str, Any]:
        """A JSON-able dict (floats round-trip exactly through Python's json)."""
        return {
            "algo": self.algo,
            "layout": dict(self.layout),
            "member_config": to_dict(self.member_config),
            "control_rate_hz": self.control_rate_hz,
            "action_low": list(self.action_low),
            "action_high": list(self.action_high),
            "obs_mean": None
            if self.obs_mean is None
            else np.asarray(self.obs_mean, float).tolist(),
            "obs_var": None if self.obs_var is None else np.asarray(self.obs_var, float).tolist(),
            "obs_clip": self.obs_clip,
            "obs_epsilon": self.obs_epsilon,
            "name": self.name,
            "base": None if self.base is None else to_dict(self.base),
            "residual_scale": list(self.residual_scale),
            "extra": self.extra,
            **({"base_plugin": self.base_plugin} if self.base_plugin else {}),
            **(
                {"obs_features": self.obs_features, "feature_size": self.feature_size}
                if self.obs_features
                else {}
            ),
        }

    @classmethod
    def from_json(cls, data: dict[str, Any], where: str = "policy metadata") -> LearnedMeta:
        try:
            member = from_dict(MemberConfig, data["member_config"], f"{where}: member_config")
            mean, var = data.get("obs_mean"), data.get("obs_var")
            base = data.get("base")
            return cls(
                algo=str(data["algo"]),
                layout={k: int(v) for k, v in data["layout"].items()},
                member_config=member,
                control_rate_hz=float(data["control_rate_hz"]),
                action_low=tuple(float(v) for v in data["action_low"]),  # type: ignore[arg-type]
                action_high=tuple(float(v) for v in data["action_high"]),  # type: ignore[arg-type]
                obs_mean=None if mean is None else np.asarray(mean, dtype=np.float64),
                obs_var=None if var is None else np.asarray(var, dtype=np.float64),
                obs_clip=float(data.get("obs_clip", 10.0)),
                obs_epsilon=float(data.get("obs_epsilon", 1e-8)),
                name=str(data.get("name", "learned")),
                base=None if base is None else from_dict(ClassicalConfig, base, f"{where}: base"),
                residual_scale=tuple(float(v) for v in data.get("residual_scale", (0.0, 0.0))),  # type: ignore[arg-type]
                extra=dict(data.get("extra", {})),
                base_plugin=str(data.get("base_plugin", "")),
                obs_features=str(data.get("obs_features", "")),
                feature_size=int(data.get("feature_size", 0)),
            )
        except KeyError as exc:
            raise InputFileError(f"{where}: missing key {exc.args[0]!r}") from None
        except (TypeError, AttributeError, ValueError) as exc:  # a value of the wrong kind
            if isinstance(exc, OpenConvoyError):
                raise
            raise InputFileError(f"{where}: bad metadata ({exc})") from None

    def normalize(self, obs: np.ndarray) -> np.ndarray:
        """The observation as the network saw it in training (VecNormalize's formula)."""
        obs = np.asarray(obs, dtype=np.float64)
        if self.obs_mean is None or self.obs_var is None:
            return obs
        z = (obs - self.obs_mean) / np.sqrt(self.obs_var + self.obs_epsilon)
        return np.clip(z, -self.obs_clip, self.obs_clip)

    def make_base(self) -> Any:
        """A fresh instance of the residual base (None for absolute actions): a
        ``ClassicalPolicy``, or the plug-in ``base_plugin`` names."""
        if self.base_plugin:
            from openconvoy.policies.plugin import load_plugin_policy

            return load_plugin_policy(self.base_plugin)
        return None if self.base is None else ClassicalPolicy(self.base)

    def make_features(self) -> Any:
        """The observation-features plug-in (None without one), checked to append the
        ``feature_size`` numbers the network was trained with."""
        if not self.obs_features:
            return None
        from openconvoy.core.plugins import features

        where = f"obs_features {self.obs_features}"
        fn, n = features(self.obs_features, int(self.layout["size"]), where)
        if n != self.feature_size:
            raise InputFileError(
                f"{where}: gives {n} features; the policy was trained with {self.feature_size}"
            )
        return fn

    def to_si(
        self, normalized_action: np.ndarray, base_action: np.ndarray | None = None
    ) -> np.ndarray:
        """Normalized action in [-1, 1]^2 (and the base's action, for residual policies)
        -> ``[speed_mps, heading_change_rad]``."""
        return compose_action(
            normalized_action, self.action_low, self.action_high, base_action, self.residual_scale
        )


def scale_action(
    normalized_action: np.ndarray, low: tuple[float, float], high: tuple[float, float]
) -> np.ndarray:
    """Map a normalized action in [-1, 1]^2 (clipped) affinely onto ``[low, high]`` (SI:
    ``[speed_mps, heading_change_rad]``); the heading change is then clipped to ±π/2."""
    a = np.clip(np.asarray(normalized_action, dtype=np.float64), -1.0, 1.0)
    lo, hi = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
    si = lo + 0.5 * (a + 1.0) * (hi - lo)
    return make_action(float(si[0]), float(si[1]))


def compose_actions(
    normalized_actions: np.ndarray,
    low: tuple[float, float],
    high: tuple[float, float],
    base_actions: np.ndarray | None = None,
    residual_scale: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    """``compose_action`` on arrays: ``(..., 2)`` normalized actions (and base actions)
    -> ``(..., 2)`` float32 SI actions, row for row the same numbers."""
    a = np.clip(np.asarray(normalized_actions, dtype=np.float64), -1.0, 1.0)
    lo, hi = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
    if base_actions is None:
        si = lo + 0.5 * (a + 1.0) * (hi - lo)
    else:
        si = np.asarray(base_actions, dtype=np.float64) + a * np.asarray(
            residual_scale, dtype=np.float64
        )
        si = np.clip(si, lo, hi)
    si[..., 1] = np.clip(si[..., 1], -MAX_HEADING_CHANGE_RAD, MAX_HEADING_CHANGE_RAD)
    return si.astype(np.float32)


def compose_action(
    normalized_action: np.ndarray,
    low: tuple[float, float],
    high: tuple[float, float],
    base_action: np.ndarray | None = None,
    residual_scale: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    """The SI action of a learned policy: ``scale_action`` without a base; with one,
    ``base_action + clip(a, -1, 1) * residual_scale`` clipped to ``[low, high]``."""
    if base_action is None:
        return scale_action(normalized_action, low, high)
    a = np.clip(np.asarray(normalized_action, dtype=np.float64), -1.0, 1.0)
    si = np.asarray(base_action, dtype=np.float64) + a * np.asarray(
        residual_scale, dtype=np.float64
    )
    si = np.clip(si, np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64))
    return make_action(float(si[0]), float(si[1]))


class LearnedPolicy:
    """A trained network behind the ``Policy`` protocol.

    ``forward(normalized_obs) -> normalized_action`` is the network (numpy or SB3);
    ``act`` normalizes the observation, runs it, and scales the action to SI units.
    The network is stateless; a residual policy's classical base keeps controller state,
    so give every follower its own copy (``copy.deepcopy``), as for classical policies.
    """

    def __init__(
        self, meta: LearnedMeta, forward: Callable[[np.ndarray], np.ndarray], source: str
    ) -> None:
        self.meta = meta
        self.layout = meta.member_config.layout
        self._forward = forward
        self._base = meta.make_base()
        self._features = meta.make_features()
        self.source = source

    @property
    def member_config(self) -> MemberConfig:
        return self.meta.member_config

    @property
    def control_rate_hz(self) -> float:
        return self.meta.control_rate_hz

    @property
    def name(self) -> str:
        return self.meta.name

    def reset(self, seed: int | None = None) -> None:
        """Forget the base's controller memory (the network has none)."""
        if self._base is not None:
            self._base.reset(seed)
        self._row_bases: list[Any] = []

    def _base_batch(self, obs: np.ndarray) -> np.ndarray:
        """A plug-in base without ``act_batch`` on a batch: one copy of it per row (each
        row a vehicle with its own memory), each acting on its row."""
        import copy

        rows = obs.reshape(-1, obs.shape[-1])
        bases = self.__dict__.setdefault("_row_bases", [])
        while len(bases) < len(rows):
            bases.append(copy.deepcopy(self._base))
        out = np.stack([np.asarray(b.act(r), dtype=np.float32) for b, r in zip(bases, rows)])
        return out.reshape(obs.shape[:-1] + (2,))

    def normalized_action(self, observation: np.ndarray) -> np.ndarray:
        """The network's deterministic action in [-1, 1]^2 (before SI scaling)."""
        obs = np.asarray(observation)
        if obs.shape != (self.layout.size,):
            raise InputFileError(
                f"observation has shape {obs.shape}, layout expects ({self.layout.size},)"
            )
        obs = self._extend(obs)
        return np.asarray(self._forward(self.meta.normalize(obs)), dtype=np.float64).reshape(-1)

    def _extend(self, rows: np.ndarray) -> np.ndarray:
        """Observations ``(..., D)`` with the features plug-in's numbers appended (as the
        network saw them in training); as given without one."""
        fn = self._features
        if fn is None:
            return rows
        flat = np.asarray(rows, dtype=np.float32).reshape(-1, rows.shape[-1])
        extra = np.stack([np.asarray(fn(r), dtype=np.float32) for r in flat])
        out = np.concatenate([flat, extra], axis=1)
        return out.reshape(rows.shape[:-1] + (out.shape[1],))

    def act(self, observation: np.ndarray) -> np.ndarray:
        a = self.normalized_action(observation)
        base = (
            None
            if self._base is None
            else self._base.act(np.asarray(observation, dtype=np.float32))
        )
        return self.meta.to_si(a, base)

    def act_batch(self, observations: np.ndarray) -> np.ndarray:
        """``act`` for a batch ``(..., D)`` -> ``(..., 2)`` float32: one forward pass of the
        network over every row; a residual base acts batched too, each row keeping its
        own controller state (``ClassicalPolicy.act_batch``; ``reset`` clears it)."""
        obs = np.asarray(observations)
        if obs.ndim < 1 or obs.shape[-1] != self.layout.size:
            raise InputFileError(
                f"observations have shape {obs.shape}, layout expects (..., {self.layout.size})"
            )
        rows = self._extend(obs.reshape(-1, self.layout.size))
        a = np.asarray(self._forward(self.meta.normalize(rows)), dtype=np.float64)
        a = a.reshape(obs.shape[:-1] + (2,))
        if self._base is None:
            base = None
        elif callable(getattr(self._base, "act_batch", None)):
            base = self._base.act_batch(obs.astype(np.float32))
        else:
            base = self._base_batch(obs.astype(np.float32))
        m = self.meta
        return compose_actions(a, m.action_low, m.action_high, base, m.residual_scale)

    def check_layout(self, layout: ObservationLayout) -> None:
        """Raise ValueError if this policy was trained for another layout than ``layout``."""
        layout.check_compatible(self.meta.layout)


class NumpyMLP:
    """The actor's forward pass in numpy: hidden layers with one activation, a linear
    output, then ``clip`` or ``tanh`` (see ``OUTPUTS``). Computes in float64.

    ``mean_clip`` > 0: the linear output is first clipped to ±``mean_clip`` (SB3's SAC with
    gSDE clips its mean with a Hardtanh before the tanh); 0: not clipped."""

    def __init__(
        self,
        weights: list[np.ndarray],
        biases: list[np.ndarray],
        activation: str,
        output: str,
        mean_clip: float = 0.0,
    ) -> None:
        if activation not in ACTIVATIONS:
            raise InputFileError(
                f"unknown activation {activation!r}; expected one of {', '.join(ACTIVATIONS)}"
            )
        if output not in OUTPUTS:
            raise InputFileError(f"unknown output {output!r}; expected one of {', '.join(OUTPUTS)}")
        if len(weights) != len(biases) or not weights:
            raise InputFileError(
                "an MLP needs as many bias vectors as weight matrices, at least one"
            )
        self.weights = [np.asarray(w, dtype=np.float64) for w in weights]
        self.biases = [np.asarray(b, dtype=np.float64) for b in biases]
        if not all(np.isfinite(a).all() for a in (*self.weights, *self.biases)):
            raise InputFileError("the network's weights are not all finite numbers (NaN or inf)")
        for i in range(1, len(self.weights)):
            if self.weights[i].shape[1] != self.weights[i - 1].shape[0]:
                raise InputFileError(
                    f"layer {i} takes {self.weights[i].shape[1]} inputs, layer {i - 1} gives {self.weights[i - 1].shape[0]}"
                )
        if not (math.isfinite(mean_clip) and mean_clip >= 0.0):
            raise InputFileError(f"mean_clip: {mean_clip!r} is not a finite number >= 0")
        self.activation = activation
        self.output = output
        self.mean_clip = float(mean_clip)
        self._act = ACTIVATIONS[activation]

    @property
    def n_inputs(self) -> int:
        return int(self.weights[0].shape[1])

    def __call__(self, x: np.ndarray) -> np.ndarray:
        h = np.asarray(x, dtype=np.float64)
        last = len(self.weights) - 1
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            h = w @ h + b if h.ndim == 1 else h @ w.T + b
            if i < last:
                h = self._act(h)
        if self.mean_clip > 0.0:
            h = np.clip(h, -self.mean_clip, self.mean_clip)
        return np.tanh(h) if self.output == "tanh" else np.clip(h, -1.0, 1.0)


def save_npz(path: str | Path, meta: LearnedMeta, mlp: NumpyMLP) -> Path:
    """Write the numpy-only artifact (no pickles: ``np.load(allow_pickle=False)`` reads it)."""
    arrays: dict[str, np.ndarray] = {
        "format": np.array(NPZ_FORMAT),
        "meta": np.array(json.dumps(meta.to_json())),
        "activation": np.array(mlp.activation),
        "output": np.array(mlp.output),
        "n_layers": np.array(len(mlp.weights)),
    }
    if mlp.mean_clip > 0.0:  # only then: the exports of other actors stay as they were
        arrays["mean_clip"] = np.array(mlp.mean_clip)
    for i, (w, b) in enumerate(zip(mlp.weights, mlp.biases)):
        arrays[f"W{i}"] = w
        arrays[f"b{i}"] = b
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)  # type: ignore[arg-type]  # numpy's stub types **kwds as allow_pickle
    return path


def load_npz(path: str | Path) -> tuple[LearnedMeta, NumpyMLP]:
    """Read an exported artifact: its metadata and its network. Anything that is not one
    (random bytes, a truncated file, missing arrays, bad metadata JSON, non-finite
    weights) is an ``InputFileError`` naming the file."""
    try:
        return _load_npz(path)
    except InputFileError as exc:
        if str(exc).startswith(str(path)):
            raise
        raise InputFileError(f"{path}: {exc}") from None
    except (ValueError, KeyError, EOFError, OSError, zipfile.BadZipFile) as exc:
        # numpy says "pickled data ... allow_pickle": the file is simply not an export
        why = "not a numpy .npz archive" if "pickle" in str(exc) else f"{type(exc).__name__}: {exc}"
        raise InputFileError(f"{path}: not a valid OpenConvoy policy export ({why})") from None


def _load_npz(path: str | Path) -> tuple[LearnedMeta, NumpyMLP]:
    with np.load(Path(path), allow_pickle=False) as data:
        if "format" not in data or str(data["format"]) != NPZ_FORMAT:
            raise InputFileError(
                f"{path}: not an OpenConvoy policy export (expected format {NPZ_FORMAT})"
            )
        meta = LearnedMeta.from_json(json.loads(str(data["meta"])), f"{path}")
        n = int(data["n_layers"])
        mlp = NumpyMLP(
            [data[f"W{i}"] for i in range(n)],
            [data[f"b{i}"] for i in range(n)],
            str(data["activation"]),
            str(data["output"]),
            float(data["mean_clip"]) if "mean_clip" in data else 0.0,
        )
    if mlp.n_inputs != meta.layout["size"] + meta.feature_size:
        raise InputFileError(
            f"{path}: the network takes {mlp.n_inputs} inputs, the layout has {meta.layout['size']}"
            + (f" and {meta.feature_size} features" if meta.feature_size else "")
        )
    return meta, mlp


def read_zip_meta(path: str | Path) -> LearnedMeta:
    """The metadata member of a trained SB3 ``.zip`` (no torch needed)."""
    try:
        with zipfile.ZipFile(path) as zf:
            if META_MEMBER not in zf.namelist():
                raise InputFileError(
                    f"{path}: an SB3 model without OpenConvoy metadata ({META_MEMBER}); "
                    "train it with `openconvoy train`"
                )
            data = json.loads(zf.read(META_MEMBER).decode("utf-8"))
    except zipfile.BadZipFile:
        raise InputFileError(f"{path}: not a zip file") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputFileError(f"{path}: {META_MEMBER} is not valid JSON ({exc})") from None
    return LearnedMeta.from_json(data, str(path))


def write_zip_meta(path: str | Path, meta: LearnedMeta) -> None:
    """Add (or replace) the metadata member of an SB3 ``.zip``."""
    path = Path(path)
    with zipfile.ZipFile(path) as zf:
        members = {n: zf.read(n) for n in zf.namelist() if n != META_MEMBER}
    tmp = path.with_suffix(".zip.tmp")
    with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, blob in members.items():
            zf.writestr(name, blob)
        zf.writestr(META_MEMBER, json.dumps(meta.to_json()))
    tmp.replace(path)


def load_sb3_model(path: str | Path, algo: str):
    """The SB3 model of a trained ``.zip`` on the CPU (imports stable-baselines3 lazily)."""
    try:
        import stable_baselines3 as sb3
    except ImportError as exc:
        raise DependencyMissing(
            f"{path}: loading an SB3 .zip needs the train extra (pip install 'openconvoy[train]'); "
            "export it to .npz with `openconvoy export` to run without torch"
        ) from exc
    from stable_baselines3.common.base_class import BaseAlgorithm

    classes: dict[str, type[BaseAlgorithm]] = {"ppo": sb3.PPO, "sac": sb3.SAC}
    if algo not in classes:
        raise InputFileError(
            f"{path}: unknown algorithm {algo!r}; expected one of {', '.join(classes)}"
        )
    # Schedules are pickled closures; inference never needs them, and replacing them avoids
    # unpickling failures across Python/SB3 versions.
    custom = {"learning_rate": 0.0, "lr_schedule": lambda _: 0.0, "clip_range": lambda _: 0.0}
    try:
        return classes[algo].load(str(path), device="cpu", custom_objects=custom)
    except Exception as exc:  # noqa: BLE001 - SB3/torch raise anything on a corrupt archive
        raise InputFileError(
            f"{path}: SB3 could not load the model ({type(exc).__name__}: {exc})"
        ) from None


def load_learned(
    path: str | Path,
    layout: ObservationLayout | None = None,
    member_config: MemberConfig | None = None,
) -> LearnedPolicy:
    """A learned policy from a ``.zip`` (SB3, needs torch) or ``.npz`` (numpy only).

    A ``.zip`` runs through the numpy forward its export runs (the actor's weights taken
    out of the SB3 model once, on load: ``openconvoy.policies.actor``), so a ``.zip`` and
    its ``.npz`` give the same actions, runs and sweeps to the bit; a ``.zip`` whose actor
    the numpy forward cannot hold (a SAC with gSDE, a custom network: nothing ``openconvoy
    train`` makes) is refused, saying why, as its export would be. ``load_sb3_predict`` is
    the reference the extraction is checked against.

    ``layout`` or ``member_config``: the convoy's observation layout; a policy trained for
    another layout is refused with a ValueError naming the difference.
    """
    path = _existing(path)
    if path.suffix == ".npz":
        meta, mlp = load_npz(path)
        forward: Callable[[np.ndarray], np.ndarray] = mlp
    elif path.suffix == ".zip":
        from openconvoy.policies.actor import actor_mlp

        meta = read_zip_meta(path)
        model = load_sb3_model(path, meta.algo)
        try:
            forward = actor_mlp(model)
        except InputFileError as exc:
            raise InputFileError(f"{path}: {exc}; it runs nowhere a .npz runs") from None
    else:
        raise InputFileError(f"{path}: a learned policy is a .zip (SB3) or .npz (export) file")
    _check_layout(path, meta, layout, member_config)
    return LearnedPolicy(meta, forward, str(path))


def load_sb3_predict(
    path: str | Path,
    layout: ObservationLayout | None = None,
    member_config: MemberConfig | None = None,
) -> LearnedPolicy:
    """A trained ``.zip`` acting through SB3's (torch) ``predict(deterministic=True)``:
    the reference an export, and ``load_learned``'s numpy forward of a ``.zip``, are
    checked against (``openconvoy export`` does, on 400 simulated observations)."""
    path = _existing(path)
    if path.suffix != ".zip":
        raise InputFileError(f"{path}: SB3's predict needs the trained .zip")
    meta = read_zip_meta(path)
    forward = _sb3_predict(load_sb3_model(path, meta.algo))
    _check_layout(path, meta, layout, member_config)
    return LearnedPolicy(meta, forward, str(path))


def _existing(path: str | Path) -> Path:
    """``path`` as a Path, a ``MissingFileError`` when no such file."""
    path = Path(path)
    if not path.is_file():
        raise MissingFileError(f"policy file not found: {path}")
    return path


def _sb3_predict(model: Any) -> Callable[[np.ndarray], np.ndarray]:
    """SB3's deterministic ``predict`` as a forward on normalized observations."""

    def predict(obs: np.ndarray) -> np.ndarray:
        action, _ = model.predict(obs.astype(np.float32), deterministic=True)
        return action

    return predict


def _check_layout(
    path: Path,
    meta: LearnedMeta,
    layout: ObservationLayout | None,
    member_config: MemberConfig | None,
) -> None:
    """Refuse (``InputFileError``, a ValueError) a policy trained for another layout."""
    for expected in (layout, None if member_config is None else member_config.layout):
        if expected is not None:
            try:
                expected.check_compatible(meta.layout)
            except ValueError as exc:
                raise InputFileError(f"{path}: {exc}") from None


__all__ = [
    "LearnedMeta",
    "LearnedPolicy",
    "NumpyMLP",
    "scale_action",
    "compose_action",
    "compose_actions",
    "load_learned",
    "load_sb3_predict",
    "load_npz",
    "save_npz",
    "read_zip_meta",
    "write_zip_meta",
    "META_MEMBER",
]
