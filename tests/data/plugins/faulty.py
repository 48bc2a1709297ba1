"""Policies that break the plug-in protocol, one way each (tests/policies/test_plugin_safety.py)."""

import time

import numpy as np


class NoAct:
    def reset(self) -> None:
        pass


class WrongSignature:
    def act(self) -> np.ndarray:
        return np.zeros(2, dtype=np.float32)


class WrongShape:
    def act(self, observation: np.ndarray) -> np.ndarray:
        return np.array([1.0, 0.0, 0.0], dtype=np.float32)


class NotANumber:
    def act(self, observation: np.ndarray) -> np.ndarray:
        return np.array([np.nan, 0.0], dtype=np.float32)


class Raises:
    def act(self, observation: np.ndarray) -> np.ndarray:
        raise RuntimeError("boom")


class Slow:
    """Sleeps ``delay_s`` (s) in every act: 200 ms is four 20 Hz control periods."""

    def __init__(self, delay_s: float = 0.2) -> None:
        self.delay_s = delay_s

    def act(self, observation: np.ndarray) -> np.ndarray:
        time.sleep(self.delay_s)
        return np.array([0.5, 0.0], dtype=np.float32)


class BadMemberConfig:
    member_config = "all-predecessors"

    def act(self, observation: np.ndarray) -> np.ndarray:
        return np.zeros(2, dtype=np.float32)


class RaisingTopology:
    """ρ that raises: refused at load, not mid-run."""

    def keeps(self, ego: int, sender: int, n_vehicles: int) -> bool:
        raise KeyError(sender)


class NanSpacing:
    """σ whose gap is NaN: refused at load."""

    def pair_gap(self, speed_mps: float, ego_length_m: float, pred_length_m: float) -> float:
        return float("nan")
