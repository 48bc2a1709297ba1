"""``VectorConvoyEnv``: the convoy rules compiled for B convoys (numba), and its adapters."""
