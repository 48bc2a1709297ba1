"""Training, tuning and export of follower policies (the ``train`` extra).

- ``train``: ``openconvoy train``, PPO/SAC with one policy shared by all followers
  (``vec``: the SuperSuit parameter-sharing VecEnv; ``randomization``: the per-episode
  world draws; ``config``: the strict TrainConfig; ``validate``: checkpoint selection).
- ``tune``: ``openconvoy tune``, Optuna over a classical policy's gains and spacing shape.
- ``export``: ``openconvoy export``, the numpy-only ``.npz`` that deploys without torch.
- ``cli``: those commands' parsers (``register``); ``commands``: their handlers.

Nothing is imported here: ``import openconvoy.train`` stays cheap, and each module pulls
in torch / stable-baselines3 / Optuna only when it needs them.
"""
