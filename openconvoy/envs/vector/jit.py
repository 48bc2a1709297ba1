"""The batched simulator's compiler: numba's ``njit``, cached on disk.

The ``VectorConvoyEnv`` kernels are loops over convoys and vehicles compiled to machine
code (numba, the ``batched`` extra), not Python loops: one call per stage of the tick
instead of ~1,000 numpy calls. The compiled code is cached, so only the first process
after an install or a change pays the compile. No ``fastmath``: the kernels keep IEEE
arithmetic, so they agree with ``ConvoyEnv``.

The kernels call the rules of ``core`` (and the plant, loss draws, traffic model) as
those modules write them: ``rules`` registers a module's plain functions on floats with
numba (``register_jitable``) when the batched package is imported, so the vehicle
runtime, which imports ``core`` alone, never needs numba, and a rule changed in its home
module changes every world.

Numba checks a cached kernel against its own source file only, but kernels call kernels
of other modules of this package and the rules of ``RULE_MODULES``: the cache lives in a
directory named for a digest of all of those files (and numba's version), so a change to
any kernel or rule recompiles every one.
``NUMBA_CACHE_DIR`` (numba's setting) moves that directory's parent; default
``~/.cache/openconvoy`` (``XDG_CACHE_HOME``; the temporary directory when not writable).
Compiling all kernels takes ~30 CPU-seconds, loading them from the cache ~1.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

from openconvoy.core.errors import DependencyMissing

try:
    import numba as _numba
    from llvmlite import ir as _ir
    from llvmlite.binding import llvm_version_info as _llvm_version
    from numba import types as _types
    from numba.core import cgutils as _cgutils
    from numba.extending import intrinsic as _intrinsic
    from numba.extending import register_jitable as _register_jitable
except ImportError as exc:  # pragma: no cover - the extra is installed by `make test`
    raise DependencyMissing(
        "VectorConvoyEnv needs numba: pip install 'openconvoy[batched]'"
    ) from exc


RULE_MODULES = (
    "openconvoy.core.estimate",
    "openconvoy.core.ladder",
    "openconvoy.core.observation",
    "openconvoy.core.ranging",
    "openconvoy.core.spacing",
    "openconvoy.core.safety",
    "openconvoy.core.state",
    "openconvoy.envs.gps",
    "openconvoy.envs.plant",
    "openconvoy.envs.reward",
    "openconvoy.envs.scenarios",
    "openconvoy.envs.traffic.state",
)
"""The modules whose plain rule functions the kernels call compiled (``rules``): their
source is part of the kernel cache's digest."""


def _rule_files() -> list[Path]:
    """The source files of ``RULE_MODULES``, found without importing them."""
    files = []
    for name in RULE_MODULES:
        spec = importlib.util.find_spec(name)
        assert spec is not None and spec.origin is not None, name
        files.append(Path(spec.origin))
    return files


def _cache_dir() -> Path:
    digest = hashlib.sha256(_numba.__version__.encode())
    for path in sorted(Path(__file__).parent.glob("*.py")):
        text = path.read_bytes()
        if b"@bare_" in text or b"@kernel" in text or b"rules(" in text or path.name == "jit.py":
            digest.update(path.name.encode() + text)
    for path in _rule_files():
        digest.update(path.name.encode() + path.read_bytes())
    home = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    base = os.environ.get("NUMBA_CACHE_DIR") or os.path.join(home, "openconvoy")
    path = Path(base) / f"vector-kernels-{digest.hexdigest()[:16]}"
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:  # a read-only home: cache in the temporary directory instead
        path = Path(tempfile.gettempdir()) / "openconvoy" / path.name
        path.mkdir(parents=True, exist_ok=True)
    return path


CACHE_DIR = _cache_dir()


def first_compile_note() -> str | None:
    """What a command says before its first batched run when this install's kernels have
    never been compiled (numba writes an index file per kernel once it has): the run
    pauses ~30–60 s, once, and the user is told why. None when they are cached."""
    if any(CACHE_DIR.glob("*.nbi")):
        return None
    return (
        "compiling the batched simulator's kernels first (once per install or upgrade, "
        f"~30-60 s; cached in {CACHE_DIR})"
    )


typeof: Callable[[Any], Any] = _numba.typeof
"""numba's type of a Python value (what a kernel is compiled for)."""


class Bound:
    """``kernel`` called through the compiled entry point of its first call's types: the
    dispatcher types every argument on every call, a named tuple's arrays in Python
    (~0.3 µs an array), more than a small batch's work. Only for one caller whose
    arguments keep their types from call to call (an env's own arrays, packed once)."""

    def __init__(self, kernel: Any) -> None:
        self.kernel: Any = kernel
        self._entry: Any = None

    def __call__(self, *args: Any) -> Any:
        if self._entry is not None:
            return self._entry(*args)
        out = self.kernel(*args)
        found = self.kernel.overloads.get(tuple(typeof(a) for a in args))
        # (``entry_point``: numba's compiled wrapper; the dispatcher stays if it is absent)
        self._entry = getattr(found, "entry_point", None) or self.kernel
        return out


_OPTIONS: dict[str, Any] = {"cache": True, "nogil": True, "error_model": "numpy"}


def kernel(fn: Callable[..., Any]) -> Any:
    """Compile ``fn`` in nopython mode, cached in ``CACHE_DIR`` (no fastmath; numpy's
    error model: a division by zero gives inf/NaN as the array code did, unchecked)."""
    return _compile(fn, _OPTIONS)


def bare_kernel(fn: Callable[..., Any]) -> Any:
    """A ``kernel`` without reference counting (numba's ``_nrt=False``): it allocates no
    array and returns none (scratch comes from the caller). A call of a kernel with
    array arguments otherwise counts each array up and down (atomic, out of line),
    which for the per-link helpers costs more than their work."""
    return _compile(fn, {**_OPTIONS, "_nrt": False})


def bare_inline(fn: Callable[..., Any]) -> Any:
    """A ``bare_kernel`` that LLVM inlines into its callers (``forceinline``): the small
    helpers called per link or per trail segment, whose arguments (each array several
    words) cost more to pass than the work."""
    return _compile(fn, {**_OPTIONS, "_nrt": False, "forceinline": True})


_REGISTERED: dict[int, Callable[..., Any]] = {}  # numba's registry is per process too


def rules(module: ModuleType, *names: str) -> None:
    """Make ``module``'s functions ``names`` (plain Python on floats and ints, one of
    ``RULE_MODULES``) callable from the kernels: numba compiles each where a kernel calls
    it, inlined, with the kernels' options (no fastmath, numpy's error model), from the
    function the module holds now. The kernels call them as ``module.name(...)``."""
    if module.__name__ not in RULE_MODULES:
        raise ValueError(
            f"{module.__name__} is not in RULE_MODULES: the kernel cache would miss its changes"
        )
    for name in names:
        fn = getattr(module, name)
        if _REGISTERED.get(id(fn)) is not fn:
            _REGISTERED[id(fn)] = fn
            _register_jitable(forceinline=True, _nrt=False, error_model="numpy")(fn)


def _compile(fn: Callable[..., Any], options: dict[str, Any]) -> Any:
    # numba reads its cache directory when a function is decorated: set it for ours only.
    config: Any = _numba.config
    saved = config.CACHE_DIR
    config.CACHE_DIR = str(CACHE_DIR)
    try:
        return _numba.njit(**options)(fn)
    finally:
        config.CACHE_DIR = saved


# The intrinsic's name carries its pointer type: opaque pointers from LLVM 15 on.
_PREFETCH = "llvm.prefetch.p0" if _llvm_version[0] >= 15 else "llvm.prefetch.p0i8"


def _prefetch(typingctx: Any, arr: Any, b: Any, ln: Any, j: Any, m: Any) -> Any:  # pragma: no cover
    """Hint the cache to fetch ``arr[b, ln, j, m]`` (a 4-D array; no effect on values):
    the batched kernels touch each convoy's trails once per tick, too far apart for the
    hardware to guess, so a kernel asks for the next convoys' rows while it works."""
    return _prefetch_at(_types.void(arr, b, ln, j, m))


def _prefetch_row(typingctx: Any, arr: Any, b: Any, ln: Any) -> Any:  # pragma: no cover
    """``prefetch`` of ``arr[b, ln, 0, ...]``'s line (an array of two or more dimensions)."""
    return _prefetch_at(_types.void(arr, b, ln))


def _prefetch_at(sig: Any) -> Any:  # pragma: no cover
    """``sig``'s prefetch intrinsic: the line of the element its indices name, the
    dimensions after them at 0."""

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        aryty = signature.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        idx = [
            context.cast(builder, v, t, _types.intp) for v, t in zip(args[1:], signature.args[1:])
        ]
        idx += [_ir.Constant(_ir.IntType(64), 0)] * (aryty.ndim - len(idx))
        ptr = _cgutils.get_item_pointer(context, builder, aryty, ary, idx)
        i8p, i32 = _ir.IntType(8).as_pointer(), _ir.IntType(32)
        fnty = _ir.FunctionType(_ir.VoidType(), [i8p, i32, i32, i32])
        fn = _cgutils.get_or_insert_function(builder.module, fnty, _PREFETCH)
        # read, high locality, data cache
        builder.call(fn, [builder.bitcast(ptr, i8p), i32(0), i32(3), i32(1)])
        return context.get_dummy_value()

    return sig, codegen


prefetch: Any = _intrinsic(_prefetch)
prefetch_row: Any = _intrinsic(_prefetch_row)
