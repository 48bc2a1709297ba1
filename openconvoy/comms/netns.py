"""Run processes inside a fresh private network namespace wired for multicast.

Tests and demos must never send multicast on a real interface (DESIGN.md, Networking
rules). ``run_in_netns`` starts commands inside a new user + network namespace
(``unshare -rn``, no root needed) that holds only loopback and a veth pair
``oc0`` <-> ``oc1``, both up, with IPv6 duplicate address detection off (so link-local
addresses are usable at once) and IPv4 addresses 10.47.0.1/24 and 10.47.0.2/24 (for the
IPv4 compatibility group). All commands share the namespace and should use interface
``oc0`` (also in ``$OPENCONVOY_NETNS_IFACE``); with multicast loop on they all hear each
other, like stations on one link. The namespace vanishes when the last command exits.

Example::

    from openconvoy.comms.netns import IFACE, require_netns, run_in_netns
    require_netns()   # RuntimeError with the reason if this machine cannot do it
    results = run_in_netns([[sys.executable, "peer.py", "0"], [sys.executable, "peer.py", "1"]],
                           timeout=30)
    for r in results: assert r.returncode == 0, r.stderr

Run as a module (``python -m openconvoy.comms.netns``) it is the inside half: it reads a
JSON spec on stdin, sets the namespace up, runs the commands, and prints their results.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

#: Interface the commands inside should use.
IFACE = "oc0"
#: The other end of the veth pair.
PEER_IFACE = "oc1"
IPV4_ADDRS = ("10.47.0.1/24", "10.47.0.2/24")
ENV_IFACE = "OPENCONVOY_NETNS_IFACE"

_ADDRESS_WAIT_S = 5.0


def netns_unavailable_reason() -> str | None:
    """Why a private network namespace cannot be made here, or None if it can."""
    if shutil.which("unshare") is None:
        return "the 'unshare' command (util-linux) is not installed"
    if shutil.which("ip") is None:
        return "the 'ip' command (iproute2) is not installed"
    try:
        r = subprocess.run(
            ["unshare", "-rn", "ip", "link", "add", "t0", "type", "veth", "peer", "name", "t1"],
            capture_output=True,
            text=True,
            timeout=20,
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"'unshare -rn' failed to run: {exc}"
    if r.returncode != 0:
        return (
            "'unshare -rn' cannot create a network namespace with a veth pair here "
            f"(unprivileged user namespaces disabled?): {r.stderr.strip()}"
        )
    return None


def require_netns() -> None:
    """Raise ``RuntimeError`` with a clear reason unless ``run_in_netns`` can work here."""
    reason = netns_unavailable_reason()
    if reason is not None:
        raise RuntimeError(f"private network namespace unavailable: {reason}")


def run_in_netns(
    commands: Sequence[Sequence[str]],
    *,
    timeout: float = 60.0,
    env: Mapping[str, str] | None = None,
    cwd: str | Path | None = None,
    stagger_s: float = 0.0,
) -> list[subprocess.CompletedProcess[str]]:
    """Run ``commands`` concurrently in one fresh network namespace; wait for all.

    Args:
        commands: argv lists, started in order (``stagger_s`` apart).
        timeout: seconds; commands still running then are killed (return code -9).
        env: environment for the commands (default: ours), plus ``OPENCONVOY_NETNS_IFACE``.
        cwd: working directory of the commands (default: ours).

    Returns one ``CompletedProcess`` (args, returncode, stdout, stderr as text) per
    command, in order. Raises ``RuntimeError`` if the namespace cannot be set up.
    """
    spec = {
        "commands": [list(map(str, c)) for c in commands],
        "timeout": timeout,
        "env": dict(os.environ if env is None else env),
        "cwd": str(cwd) if cwd is not None else os.getcwd(),
        "stagger_s": stagger_s,
    }
    try:
        outer = subprocess.run(
            ["unshare", "-rn", sys.executable, "-m", "openconvoy.comms.netns"],
            input=json.dumps(spec),
            capture_output=True,
            text=True,
            timeout=timeout + 30.0,
        )
    except FileNotFoundError:
        raise RuntimeError("the 'unshare' command (util-linux) is not installed") from None
    except subprocess.TimeoutExpired:
        raise RuntimeError(
            f"network namespace did not finish within {timeout + 30:.0f} s"
        ) from None
    if outer.returncode != 0:
        raise RuntimeError(
            f"network namespace setup failed (exit {outer.returncode}): {outer.stderr.strip()}"
        )
    try:
        results = json.loads(outer.stdout)
    except ValueError:
        raise RuntimeError(f"bad output from the namespace: {outer.stdout[:500]!r}") from None
    return [
        subprocess.CompletedProcess(r["args"], r["returncode"], r["stdout"], r["stderr"])
        for r in results
    ]


# --- inside the namespace ---------------------------------------------------------------


def _ip(*args: str) -> None:
    r = subprocess.run(["ip", *args], capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {r.stderr.strip()}")


def _write_sysctl(path: str, value: str) -> None:
    with open(path, "w") as f:
        f.write(value)


def setup_network() -> str:
    """Wire the current, fresh network namespace for multicast; return the interface name.

    For code that enters the namespace itself (``unshare -rn python -m ...``, as the demo
    does) instead of going through ``run_in_netns``. Refuses (``RuntimeError``) unless
    the namespace holds nothing but loopback, so it can never touch a real host's network.
    """
    import socket

    others = [name for _, name in socket.if_nameindex() if name != "lo"]
    if others:
        raise RuntimeError(
            "setup_network() must run in a fresh private network namespace "
            f"(unshare -rn); this one has interfaces {', '.join(others)}"
        )
    _setup_network()
    return IFACE


def _setup_network() -> None:
    # DAD off before the links exist, so their link-local addresses are never tentative
    # (a tentative address cannot source multicast).
    for scope in ("all", "default"):
        _write_sysctl(f"/proc/sys/net/ipv6/conf/{scope}/accept_dad", "0")
    _ip("link", "set", "lo", "up")
    _ip("link", "add", IFACE, "type", "veth", "peer", "name", PEER_IFACE)
    for dev, addr in zip((IFACE, PEER_IFACE), IPV4_ADDRS):
        _ip("addr", "add", addr, "dev", dev)
        _ip("link", "set", dev, "up")
    deadline = time.monotonic() + _ADDRESS_WAIT_S
    while True:
        out = subprocess.run(
            ["ip", "-6", "addr", "show", "dev", IFACE], capture_output=True, text=True
        ).stdout
        if "inet6 fe80" in out and "tentative" not in out:
            return
        if time.monotonic() > deadline:
            raise RuntimeError(f"no usable IPv6 link-local address on {IFACE}: {out}")
        time.sleep(0.02)


def _inside(spec: dict) -> list[dict]:
    setup_network()
    env = {**spec["env"], ENV_IFACE: IFACE}
    procs = []
    with tempfile.TemporaryDirectory(prefix="openconvoy-netns-") as tmp:
        for i, argv in enumerate(spec["commands"]):
            if i and spec.get("stagger_s"):
                time.sleep(spec["stagger_s"])
            out = open(Path(tmp) / f"{i}.out", "w+")
            err = open(Path(tmp) / f"{i}.err", "w+")
            p = subprocess.Popen(argv, stdout=out, stderr=err, env=env, cwd=spec["cwd"], text=True)
            procs.append((argv, p, out, err))
        deadline = time.monotonic() + spec["timeout"]
        results = []
        for argv, p, out, err in procs:
            try:
                rc = p.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                rc = p.wait()
            out.seek(0)
            err.seek(0)
            results.append(
                {"args": argv, "returncode": rc, "stdout": out.read(), "stderr": err.read()}
            )
            out.close()
            err.close()
    return results


def main() -> int:
    spec = json.loads(sys.stdin.read())
    try:
        results = _inside(spec)
    except (RuntimeError, OSError) as exc:
        print(f"openconvoy.comms.netns: {exc}", file=sys.stderr)
        return 1
    json.dump(results, sys.stdout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
