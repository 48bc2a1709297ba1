"""The classical policy on arrays: ``ClassicalPolicy.act`` for a whole batch at once.

``BatchedClassical(config).act_batch(obs)`` takes observations shaped ``(..., D)`` (for
example ``(B, N-1, D)`` from ``envs.VectorConvoyEnv``) and returns actions ``(..., 2)``,
float32, equal to what one ``ClassicalPolicy`` per row would return for the same
sequence of observations, with each row's PID integrator kept separately. The
per-vehicle ``act`` is unchanged (vehicles use it).

The rows are ``policies.classical_rows.act_rows``, written once: with numba (the
``batched`` extra) compiled (``policies.batched_jit``, ~40 µs for 1,024 x 2 rows);
without it run as Python (the same bits, ~1,000 times slower: for a few rows only).
"""

from __future__ import annotations

from types import ModuleType

import numpy as np

from openconvoy.core.errors import ConfigError, DependencyMissing
from openconvoy.policies import classical_rows
from openconvoy.policies.classical import ClassicalConfig

_jit: ModuleType | None
try:
    from openconvoy.policies import batched_jit as _jit
except DependencyMissing:  # numba comes with the batched extra; Python runs the same rows
    _jit = None


class BatchedClassical:
    """The classical policy of ``config`` for a batch of vehicles (rows). ``compiled``:
    act through ``batched_jit``'s kernel (None: when numba is importable)."""

    def __init__(self, config: ClassicalConfig, compiled: bool | None = None) -> None:
        """The rows ``ClassicalPolicy.act`` runs for ``config``, compiled or as Python
        (tests/policies/test_batched_jit.py::test_the_rows_are_act_on_random_observations)."""
        if config.speed.is_plugin or config.heading.is_plugin:
            raise ConfigError(
                "act_batch computes the built-in controllers only; a plug-in speed or heading "
                "controller acts per vehicle (act)"
            )
        self.config = config
        self.layout = config.member.layout
        self._integral: np.ndarray | None = None
        if compiled and _jit is None:
            raise DependencyMissing(
                "compiled act_batch needs numba: pip install 'openconvoy[batched]'"
            )
        use = _jit is not None if compiled is None else compiled
        self._rows = _jit.act_rows if use and _jit is not None else classical_rows.act_rows
        self._packed = classical_rows.pack(config)

    @property
    def compiled(self) -> bool:
        """Whether ``act_batch`` runs the compiled kernel of ``ClassicalPolicy.act``'s rows (tests/policies/test_batched_jit.py::test_the_rows_are_act_on_random_observations)."""
        return self._rows is not classical_rows.act_rows

    def reset(self, seed: int | None = None) -> None:
        """Forget every row's controller state."""
        self._integral = None

    def reset_rows(self, rows: np.ndarray) -> None:
        """Forget the state of the rows where ``rows`` (bool, the batch shape) is True
        (convoys that started a new episode), as ``ClassicalPolicy.reset`` forgets one
        vehicle's (tests/policies/test_batched_jit.py::test_the_rows_are_act_on_random_observations)."""
        if self._integral is not None:
            self._integral[rows] = 0.0

    def act_batch(self, observations: np.ndarray) -> np.ndarray:
        """Actions ``(..., 2)`` float32 (SI: speed m/s, heading change rad): each row's
        ``ClassicalPolicy.act``, bit for bit (tests/policies/test_batched_jit.py::test_the_rows_are_act_on_random_observations)."""
        obs = np.asarray(observations, dtype=np.float32)
        if obs.shape[-1] != self.layout.size:
            raise ValueError(
                f"observations have {obs.shape[-1]} features, layout expects {self.layout.size}"
            )
        shape = obs.shape[:-1]
        if self._integral is None or self._integral.shape != shape:
            self._integral = np.zeros(shape)
        rows = np.ascontiguousarray(obs.reshape(-1, obs.shape[-1]))
        integral = self._integral.reshape(-1)  # a view: the rows update it in place
        out = np.empty((rows.shape[0], 2), dtype=np.float32)
        self._rows(rows, integral, *self._packed, out)
        return out.reshape(shape + (2,))
