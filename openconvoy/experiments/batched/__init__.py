"""Batched sweeps: a policy's runs as the convoys of one ``VectorConvoyEnv``."""
