"""Compiled C rollouts for the cross-entropy planner, same guard logic as the simulator.

The system's numeric pieces (per mode: RK4 step, guard gaps, gaps along the RK4 sub-step;
per guard: activity region and reset; the stage cost) are generated as C by CasADi from the
same SX graphs as :class:`~hmpc_cli.core.hybrid.NumericSystem`. ``rollout_kernel.c`` (hand
written) runs the planner's rollouts with the event location of
:class:`~hmpc_cli.sim.simulator.HybridSimulator`, keeping the NumPy batch semantics (the samples of
one event search iterate together until all converge), so its results are NumPy's bit for
bit when both evaluate the elementary operations alike (IEEE +, -, *, /, sqrt; libm and
NumPy may differ in the last bit of sin, exp, ...). The shared library is compiled once per
machine and source (in a thread, so a caller can build other things meanwhile:
:func:`start_library`), cached under a hash of source, flags and the compiler's identity (its
path and ``--version`` output) in ``$HMPC_CACHE_DIR`` (default ``~/.cache/hmpc``), written
atomically with its sha256 next to it (``.sha256``), and loaded with ctypes only when that
hash matches (a truncated or replaced library is rebuilt, never executed). A cache directory
writable by group or others, or owned by another user, is not used: the library is then
built in a private temporary directory (with a warning).
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import tempfile
import threading
from importlib import resources
from pathlib import Path

import casadi as ca
import numpy as np

from hmpc_cli.core.cbuild import (
    CBuildError,
    checked_cache_dir,
    compile_shared,
    compiler,
    compiler_problem,
    compiler_identity,
    private_dir,
    verified,
)
from hmpc_cli.core.hybrid import HybridSystem, rk4_expr

#: -O1: compiles in about 60 % of -O2's time with plans as fast (docs/performance.md);
#: no flag here changes a number (no contraction, no fast-math)
CFLAGS = ("-O1", "-shared", "-fPIC", "-ffp-contract=off", "-fvisibility=hidden")
ABI = 4  # must equal HM_ABI of rollout_kernel.c
COMPILES = 0  # compilations done by this process (the cache makes repeats free)
_LIBS: dict[str, ctypes.CDLL] = {}  # loaded libraries by path
_FAILED: dict[tuple[str, tuple[str, ...]], str] = {}  # failed builds by path and compiler
_PENDING: dict[str, LibraryBuild] = {}  # compiles under way in this process, by path
_LOCK = threading.Lock()  # _LIBS, _FAILED and _PENDING (a process's threads share builds)
_D = ctypes.POINTER(ctypes.c_double)
_LOG = logging.getLogger(__name__)


class RolloutBuildError(CBuildError):
    """The C rollout could not be generated, compiled or loaded."""


def _sx(name: str, fun: ca.Function, x: ca.SX) -> ca.Function:
    """fun(x) as an SX function called ``name`` (same expression graph)."""
    if not fun.is_a("SXFunction"):
        fun = fun.expand()
    return ca.Function(name, [x], [fun(x)])


def system_functions(system: HybridSystem) -> dict[str, ca.Function]:
    """The SX functions the kernel calls, keyed by their C names.

    Built exactly as :class:`~hmpc_cli.core.hybrid.NumericSystem` builds its NumPy evaluators:
    ``hm_rk4_i`` (x, u, w, h) -> x_h, ``hm_gaps_i`` x -> gaps of mode i's guards,
    ``hm_phi_i`` (x, u, w, h) -> (gaps, rates, x_h), ``hm_region_j`` / ``hm_reset_j`` of
    guard j, and ``hm_L`` (x, u) -> stage cost.
    """
    x = ca.SX.sym("x", system.n_x)
    u = ca.SX.sym("u", system.n_u)
    w = ca.SX.sym("w", system.n_w)
    h = ca.SX.sym("h")
    funs: dict[str, ca.Function] = {}
    for i, mode in enumerate(system.modes):
        funs[f"hm_rk4_{i}"] = ca.Function(f"hm_rk4_{i}", [x, u, w, h],
                                          [rk4_expr(mode, x, u, w, h)])
        guards = system.guards_of(i)
        if not guards:
            continue
        gaps = ca.vertcat(*[system.guards[g].gap_expr(x) for g in guards], ca.SX(0, 1))
        funs[f"hm_gaps_{i}"] = ca.Function(f"hm_gaps_{i}", [x], [gaps])
        x_tau = rk4_expr(mode, x, u, w, h)
        u_sat = ca.fmin(ca.fmax(u, ca.DM(mode.u_lower)), ca.DM(mode.u_upper))
        rate = ca.jtimes(gaps, x, mode.flow(x, u_sat, w))
        phi, dphi = ca.Function("at_tau", [x, u, w], [gaps, rate])(x_tau, u, w)
        funs[f"hm_phi_{i}"] = ca.Function(f"hm_phi_{i}", [x, u, w, h], [phi, dphi, x_tau])
    for j, g in enumerate(system.guards):
        if g.region is not None:
            funs[f"hm_region_{j}"] = _sx(f"hm_region_{j}", g.region, x)
        funs[f"hm_reset_{j}"] = _sx(f"hm_reset_{j}", g.reset, x)
    funs["hm_L"] = ca.Function("hm_L", [x, u], [system.stage_cost(x, u)])
    return funs


def _table(ctype: str, name: str, values: list) -> str:
    values = values or [0]
    return f"static {ctype} const {name}[] = {{{', '.join(str(v) for v in values)}}};\n"


def _doubles(values) -> list[str]:
    return [repr(float(v)) if np.isfinite(v) else ("INFINITY" if v > 0 else "-INFINITY")
            for v in values]


def generate_source(system: HybridSystem) -> str:
    """Full C source: CasADi-generated functions, the system's tables, the kernel."""
    funs = system_functions(system)
    cg = ca.CodeGenerator("hm_sys", {"with_header": False, "casadi_real": "double",
                                     "casadi_int": "long long int"})
    for f in funs.values():
        cg.add(f)
    n_modes, n_guards = len(system.modes), len(system.guards)
    guards_of = [system.guards_of(i) for i in range(n_modes)]
    max_g = max([len(g) for g in guards_of] + [1])
    n_region = [funs[f"hm_region_{j}"].nnz_out(0) if f"hm_region_{j}" in funs else 0
                for j in range(n_guards)]
    defs = {"HM_NX": system.n_x, "HM_NU": system.n_u, "HM_NW": system.n_w,
            "HM_NMODES": n_modes, "HM_NGUARDS": n_guards, "HM_MAXG": max_g,
            "HM_MAXR": max(n_region + [1]),
            "HM_SZ_ARG": max(f.sz_arg() for f in funs.values()),
            "HM_SZ_RES": max(f.sz_res() for f in funs.values()),
            "HM_SZ_IW": max(f.sz_iw() for f in funs.values()),
            "HM_SZ_W": max(f.sz_w() for f in funs.values())}
    fn = "hm_fn"
    tab = "\n/* ---- system tables (generated by hmpc_cli/sim/rollout.py) ---- */\n"
    tab += "#include <math.h>\n"
    tab += "".join(f"#define {k} {v}\n" for k, v in defs.items())
    tab += (f"typedef int (*{fn})(const casadi_real**, casadi_real**, casadi_int*, "
            "casadi_real*, int);\n")

    def ptrs(prefix: str, count: int) -> list[str]:
        return [f"{prefix}{i}" if f"{prefix}{i}" in funs else "0" for i in range(count)]

    tab += _table(fn, "hm_rk4", ptrs("hm_rk4_", n_modes))
    tab += _table(fn, "hm_gaps", ptrs("hm_gaps_", n_modes))
    tab += _table(fn, "hm_phi", ptrs("hm_phi_", n_modes))
    tab += _table(fn, "hm_region", ptrs("hm_region_", n_guards))
    tab += _table(fn, "hm_reset", ptrs("hm_reset_", n_guards))
    tab += _table("int", "hm_nregion", n_region)
    tab += _table("int", "hm_ng", [len(g) for g in guards_of])
    rows = ["{" + ", ".join(str(v) for v in g + [-1] * (max_g - len(g))) + "}"
            for g in guards_of]
    tab += f"static int const hm_guard[][HM_MAXG] = {{{', '.join(rows)}}};\n"
    tab += _table("int", "hm_target", [system.mode_index(g.target) for g in system.guards])
    for name, attr in (("hm_ulo", "u_lower"), ("hm_uhi", "u_upper")):
        rows = ["{" + ", ".join(_doubles(getattr(m, attr))) + "}" for m in system.modes]
        tab += f"static double const {name}[][HM_NU] = {{{', '.join(rows)}}};\n"
    tab += f"static {fn} const hm_cost = hm_L;\n"
    kernel = resources.files("hmpc_cli.sim").joinpath("rollout_kernel.c").read_text()
    return cg.dump() + tab + "\n" + kernel


def _safe_cache_dir() -> Path:
    """The cache directory if it is safe, else a private temporary one (with a warning)."""
    folder, reason = checked_cache_dir()
    return private_dir("C rollout", folder, reason) if reason else folder


def _load(path: Path) -> ctypes.CDLL:
    lib = ctypes.CDLL(str(path))
    if lib.hm_abi() != ABI:
        raise OSError(f"{path}: kernel ABI {lib.hm_abi()} != {ABI}")
    ptr, i, d = ctypes.c_void_p, ctypes.c_int, ctypes.c_double
    lib.hm_rollout.argtypes = [i, i, _D, i, _D, d, d, i, i, d, d, i, _D, ptr]
    lib.hm_rollout.restype = i
    lib.hm_step.argtypes = [i, _D, ptr, _D, d, i, d, _D, ptr, ptr]
    lib.hm_step.restype = i
    lib.hm_trajectory.argtypes = [i, _D, i, _D, d, i, i, d, i, _D, ptr, ptr, ptr, _D, ptr, _D, _D,
                                  ptr]
    lib.hm_trajectory.restype = i
    return lib


def build_library(source: str) -> tuple[ctypes.CDLL, Path, float | None]:
    """Loads the library of ``source``, compiling it first if no verified copy is cached.

    Returns:
        The library, its path, and the compile time [s] (None if it was cached).

    Raises:
        RolloutBuildError: no compiler, the compilation failed, or the library won't load.
    """
    return start_library(source).result()


def start_library(source: str) -> LibraryBuild:
    """The library of ``source``: loaded if a verified copy is cached, else compiling.

    The compile runs in a thread (the compiler is a child process), so the caller can
    build other things meanwhile; :meth:`LibraryBuild.result` waits for it. A library of
    the same source already compiling in this process is shared, not compiled twice.

    Raises:
        RolloutBuildError: no usable compiler, or this build already failed in this process.
    """
    cc = compiler()
    if cc is None:
        raise RolloutBuildError(compiler_problem() or
                                "no C compiler found (set CC or install cc/gcc)")
    try:
        identity = compiler_identity(cc)
    except CBuildError as e:
        raise RolloutBuildError(str(e)) from e
    key = hashlib.sha256("\0".join([source, *CFLAGS, identity]).encode())
    path = _safe_cache_dir() / f"rollout-{key.hexdigest()[:24]}.so"
    with _LOCK:
        if str(path) in _LIBS:
            return LibraryBuild(path, _LIBS[str(path)])
        if str(path) in _PENDING:
            return _PENDING[str(path)]
        if verified(path):
            try:
                _LIBS[str(path)] = _load(path)
                return LibraryBuild(path, _LIBS[str(path)])
            except (OSError, AttributeError):
                pass  # stale: rebuild
        elif path.exists():
            _LOG.warning("%s does not match its recorded sha256: rebuilding it", path)
        failed = _FAILED.get((str(path), tuple(cc)))
        if failed:
            raise RolloutBuildError(failed)
        _PENDING[str(path)] = LibraryBuild(path, compile_with=(cc, source))
        return _PENDING[str(path)]


class LibraryBuild:
    """A rollout library, loaded or being compiled (:func:`start_library` makes them).

    Args:
        path: the library's cache path.
        lib: the loaded library (nothing to compile), or None.
        compile_with: (compiler command, C source): compiled in a new thread.
    """

    def __init__(self, path: Path, lib: ctypes.CDLL | None = None,
                 compile_with: tuple[list[str], str] | None = None) -> None:
        self.path = path
        self._result = None if lib is None else (lib, path, None)
        self._seconds: float | None = None
        self._error: RolloutBuildError | None = None
        self._cc: list[str] = []
        self._thread: threading.Thread | None = None
        if compile_with is not None:
            self._cc, source = compile_with
            # not a daemon: an ordinary exit during the compile waits for it (the library
            # is then cached, and no temporary file is left beside it)
            self._thread = threading.Thread(target=self._compile, args=(source,),
                                            name="hmpc-rollout-compile")
            self._thread.start()

    @property
    def done(self) -> bool:
        """Whether the compile (if any) has finished: :meth:`result` returns at once."""
        return self._thread is None or not self._thread.is_alive()

    def _compile(self, source: str) -> None:
        try:
            self._seconds = _compile(self._cc, source, self.path)
        except RolloutBuildError as e:
            self._error = e
        except Exception as e:  # any other failure: raised by result(), in its caller
            self._error = RolloutBuildError(f"compiling {self.path.name} failed: {e}")

    def result(self) -> tuple[ctypes.CDLL, Path, float | None]:
        """(library, path, compile seconds or None if cached), once the compile is done.

        Raises:
            RolloutBuildError: the compilation failed, or the library won't load.
        """
        if self._result is not None:
            return self._result
        thread = self._thread
        if thread is not None:
            thread.join()
        key = str(self.path)
        with _LOCK:
            if _PENDING.get(key) is self:
                del _PENDING[key]
            if self._error is not None:
                _FAILED[(key, tuple(self._cc))] = str(self._error)
                raise self._error
            if key not in _LIBS:
                try:
                    _LIBS[key] = _load(self.path)
                except (OSError, AttributeError) as e:
                    self._error = RolloutBuildError(f"cannot load {self.path}: {e}")
                    raise self._error from e
            self._result = (_LIBS[key], self.path, self._seconds)
            return self._result


def _compile(cc: list[str], source: str, path: Path) -> float:
    """Compiles ``source`` to ``path`` atomically with its sha256; returns seconds."""
    global COMPILES
    with tempfile.TemporaryDirectory() as work:
        src = Path(work) / (path.stem + ".c")
        src.write_text(source)
        try:
            seconds = compile_shared(cc, CFLAGS, src, path, timeout=300)
        except CBuildError as e:
            raise RolloutBuildError(str(e)) from e
    COMPILES += 1
    _LOG.info("compiled the C rollouts in %.2f s: %s", seconds, path)
    return seconds


class CRollout:
    """The planner's rollout in compiled C for one system.

    Args:
        system: the hybrid system.
        max_events: events per step before Zeno (as the simulator's).
        time_tol: event time bracket [s] (as the simulator's).
        wait: wait for the library here; else it may still be compiling
            (:meth:`wait`, or the first call, waits for it).

    Attributes:
        path: the shared library. compile_seconds: compile time, None if cached (or not
            waited for yet).

    Raises:
        RolloutBuildError: code generation, compilation or loading failed (with
            ``wait=False``, a failed compilation is raised by :meth:`wait` instead).
    """

    def __init__(self, system: HybridSystem, max_events: int = 10, time_tol: float = 1e-10,
                 *, wait: bool = True):
        self.n_x, self.n_u = system.n_x, system.n_u
        self.max_events, self.time_tol = int(max_events), float(time_tol)
        try:
            source = generate_source(system)
        except Exception as e:  # any code generation failure means: no C backend
            raise RolloutBuildError(f"C code generation failed: {e}") from e
        self._build = start_library(source)
        self.path = self._build.path
        self._lib: ctypes.CDLL | None = None
        self.compile_seconds: float | None = None
        if wait:
            self.wait()

    @property
    def ready(self) -> bool:
        """Whether the library is loaded (:meth:`wait` returns at once)."""
        return self._lib is not None

    def wait(self) -> None:
        """Waits for the library to be compiled and loads it.

        Raises:
            RolloutBuildError: the compilation failed, or the library won't load.
        """
        if self._lib is None:
            self._lib, _, self.compile_seconds = self._build.result()

    @property
    def lib(self) -> ctypes.CDLL:
        """The loaded library (waits for its compilation)."""
        self.wait()
        return self._lib

    def cost(self, x0: np.ndarray, mode0: int, u: np.ndarray, dt: float, final_mode: int,
             bound: float, penalty: float, absorbing: bool = True
             ) -> tuple[np.ndarray, np.ndarray]:
        """Costs (B,) and final-domain flags (B,) of step inputs u (B, n_steps, m).

        Same as ``CrossEntropyPlanner.rollout_cost_numpy`` on the same batch, bit for bit.
        ``absorbing``: the final domain ends a rollout (cost "hmpc"); else every rollout
        runs the whole horizon and the flag says whether it ever entered (cost "reference").
        """
        x0 = np.ascontiguousarray(x0, dtype=float)
        u = np.ascontiguousarray(u, dtype=float)
        b, n_steps = u.shape[0], u.shape[1]
        if x0.shape != (self.n_x,) or u.shape[2] != self.n_u:
            raise ValueError(f"shapes x0 {x0.shape}, u {u.shape} do not fit the system")
        cost = np.empty(b)
        reached = np.zeros(b, dtype=np.uint8)
        status = self.lib.hm_rollout(b, n_steps, x0.ctypes.data_as(_D), int(mode0),
                                     u.ctypes.data_as(_D), float(dt), float(bound),
                                     int(final_mode), self.max_events, self.time_tol,
                                     float(penalty), int(bool(absorbing)),
                                     cost.ctypes.data_as(_D),
                                     reached.ctypes.data)
        _check(status)
        return cost, reached.astype(bool)

    def step(self, x: np.ndarray, mode: np.ndarray, u: np.ndarray, dt: float):
        """``HybridSimulator.step`` of a batch with zero disturbance and raise_zeno=False.

        Args: x (B, n), mode (B,), u (B, m), dt [s]. Returns x (B, n), mode (B,), zeno (B,).
        """
        x = np.ascontiguousarray(x, dtype=float)
        mode = np.ascontiguousarray(mode, dtype=np.intc)
        u = np.ascontiguousarray(u, dtype=float)
        b = x.shape[0]
        if x.shape != (b, self.n_x) or u.shape != (b, self.n_u) or mode.shape != (b,):
            raise ValueError(f"shapes x {x.shape}, mode {mode.shape}, u {u.shape} do not fit")
        x_out, mode_out = np.empty_like(x), np.empty_like(mode)
        zeno = np.zeros(b, dtype=np.uint8)
        status = self.lib.hm_step(b, x.ctypes.data_as(_D), mode.ctypes.data,
                                  u.ctypes.data_as(_D), float(dt), self.max_events,
                                  self.time_tol, x_out.ctypes.data_as(_D), mode_out.ctypes.data,
                                  zeno.ctypes.data)
        _check(status)
        return x_out, mode_out.astype(int), zeno.astype(bool)


    def trajectory(self, x0: np.ndarray, mode0: int, u: np.ndarray, dt: float,
                   final_mode: int) -> list[tuple[np.ndarray, int, list[tuple]]]:
        """Steps one sample in C (the same steps as the NumPy simulator).

        Stops after the step that ends in Zeno chattering, a non-finite state or
        ``final_mode``.

        Args:
            x0: initial state (n,).
            mode0: initial mode index.
            u: inputs (n_steps, m), one held over each step.
            dt: step [s].
            final_mode: mode index that ends the rollout.

        Returns:
            Per step taken: (x after (n,), mode after, events as (tau [s] into the step,
            guard, state before (n,), state after (n,)) in time order).

        Raises:
            ValueError: x0 or u has the wrong shape, or a mode index is out of range.
        """
        x0 = np.ascontiguousarray(x0, dtype=float)
        u = np.ascontiguousarray(u, dtype=float)
        n_steps, n = u.shape[0], self.n_x
        if x0.shape != (n,) or u.shape != (n_steps, self.n_u):
            raise ValueError(f"shapes x0 {x0.shape}, u {u.shape} do not fit the system")
        cap = n_steps * (self.max_events + 1)
        xs, modes = np.empty((n_steps, n)), np.empty(n_steps, dtype=np.intc)
        ev_step, ev_guard = np.empty(cap, dtype=np.intc), np.empty(cap, dtype=np.intc)
        ev_tau, before, after = np.empty(cap), np.empty((cap, n)), np.empty((cap, n))
        n_done, n_ev = ctypes.c_int(0), ctypes.c_int(0)
        status = self.lib.hm_trajectory(
            n_steps, x0.ctypes.data_as(_D), int(mode0), u.ctypes.data_as(_D), float(dt),
            int(final_mode), self.max_events, self.time_tol, cap, xs.ctypes.data_as(_D),
            modes.ctypes.data, ctypes.byref(n_done), ev_step.ctypes.data,
            ev_tau.ctypes.data_as(_D), ev_guard.ctypes.data, before.ctypes.data_as(_D),
            after.ctypes.data_as(_D), ctypes.byref(n_ev))
        _check(status)
        events: list[list[tuple]] = [[] for _ in range(n_done.value)]
        for j in range(n_ev.value):
            events[ev_step[j]].append((float(ev_tau[j]), int(ev_guard[j]), before[j], after[j]))
        return [(xs[k], int(modes[k]), events[k]) for k in range(n_done.value)]


def _check(status: int) -> None:
    if status == -1:
        raise ValueError("mode index out of range")
    if status == -3:
        raise RuntimeError("C trajectory: more events than recorded")
    if status != 0:
        raise MemoryError("C rollout: out of memory")
