"""Render a cut-in on the highway as an animated GIF (the one at the top of the README;
needs the ``traffic`` and ``plots`` extras).

``highway-cut-in``: a car without V2V paces the convoy's first gap, cuts into it at 3 s and
leaves at 8 s. The followers run ``cacc-allpred+ladder``: green while they cooperate over
V2V, orange while they follow the intruder by radar. ``env.render()`` gives each frame.

    python examples/render_cut_in.py [--seconds 14] [--out docs/cut-in.gif]
"""

from __future__ import annotations

import argparse
import copy
from pathlib import Path

from PIL import Image

from openconvoy.envs import ConvoyEnv
from openconvoy.policies.spec import load_policy


def render(out: Path, seconds: float = 14.0, seed: int = 0, every: int = 4) -> int:
    """Write the GIF (one frame every ``every`` ticks, played in real time); the number of
    frames written."""
    policy = load_policy("cacc-allpred+ladder")
    env = ConvoyEnv(
        "highway-cut-in",
        member_config=policy.member_config,
        control_rate_hz=float(policy.control_rate_hz),
        render_mode="rgb_array",
    )
    policies = {a: copy.deepcopy(policy) for a in env.possible_agents}
    obs, _ = env.reset(seed=seed)
    for p in policies.values():
        p.reset(seed)
    frames = []
    for tick in range(int(seconds * env.control_rate_hz)):
        if not env.agents:
            break
        obs, *_ = env.step({a: policies[a].act(obs[a]) for a in env.agents})
        if tick % every == 0:
            frame = Image.fromarray(env.render())
            frames.append(frame.convert("P", palette=Image.Palette.ADAPTIVE, colors=64))
    env.close()
    out.parent.mkdir(parents=True, exist_ok=True)
    frames[0].save(
        out,
        save_all=True,
        append_images=frames[1:],
        duration=int(1000 * every / env.control_rate_hz),
        loop=0,
        optimize=True,
    )
    return len(frames)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=14.0)
    parser.add_argument("--out", type=Path, default=Path("docs/cut-in.gif"))
    args = parser.parse_args()
    n = render(args.out, args.seconds)
    print(f"wrote {args.out} ({n} frames)")
