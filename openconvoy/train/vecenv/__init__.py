"""SB3 VecEnvs for parameter sharing: SuperSuit-based, batched, and randomized."""
