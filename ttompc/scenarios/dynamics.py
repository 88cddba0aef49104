"""A scenario's dynamics written once (``CompiledStep``): one numba-compatible step function, from which a
``CompiledScenario`` derives the exact numpy step (``Scenario.step``), the SCP's affine model with its Jacobians
(``Scenario.convex_model``, by complex steps), the batched torch model of the rollout (``Scenario.batched_model``) and
the fused decoder's compiled step (``BatchedModel.fused_step``), so that none of them is written twice. A scenario may
override any of them with a faster hand-written form; ``ttompc check-scenario`` checks every form against ``step``.

The function, ``func(x, u, k, p, out)``, is plain Python that numba compiles (``numba.cfunc``): scalar arithmetic,
loops, ``math``/NumPy scalar functions and module-level constants, indexing its arguments: the state x (n,) and
control u (m,) at absolute step k and the problem's parameter row p (P,), writing x_{k+1} into out (n,) (which never
aliases x or u). It runs in float64 for the numpy step and the torch model's float64 states, in float32 for float32
ones and the fused decode, in complex128 for the Jacobians (so it must be analytic in x and u: NumPy functions, no
``abs``, ``min`` or comparisons of them); it may call no compiled code from other files (its cache is keyed on its
own file, ``ttompc.compiled``).

Measured against hand-written forms in one run (``bench/dynamics_forms.py``, docs/benchmarks.md): the derived torch
step is 1.7-3× faster than the torch code it replaced and the derived NumPy step 1.3-2.3× faster for the quadrotor,
which derives both; hand-written Jacobians stay faster than complex steps (1.2× for the quadrotor's, 6× for the
free-flyer's constant matrices), and so does the free-flyer's NumPy step (two matrix products, 1.05-1.8×).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from ttompc.compiled import Kernel, own_file_kernel
from ttompc.scenarios.base import ConvexModel, Problem, Scenario, Window

Row = Sequence[float] | np.ndarray  # a problem's parameter row


def _call_step(typingctx: Any, address: Any, x: Any, u: Any, k: Any, p: Any, out: Any) -> Any:
    """``call_step``, in compiled code: the compiled step at ``address`` (``CompiledStep.cfunc(dtype).address``) on
    the 1-D arrays x, u, p and out of that dtype at step k. A call by address: a cfunc passed as an argument costs
    about 50 µs a call to unbox from Python (measured: 65 µs against 1.8 µs for the same loop), an integer nothing."""
    arrays = (x, u, p, out)
    if not isinstance(address, types.Integer) or not all(
        isinstance(a, types.Array) and a.dtype == x.dtype and a.ndim == 1 for a in arrays
    ):
        return None  # numba reports the call as untyped
    sig = types.void(address, x, u, k, p, out)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        address, xv, uv, kv, pv, outv = args
        xp, up, pp, op = (
            cgutils.create_struct_proxy(ty)(context, builder, value=v).data
            for ty, v in zip(arrays, (xv, uv, pv, outv), strict=True)
        )
        step_k = context.cast(builder, kv, signature.args[3], types.intp)
        fnty = ir.FunctionType(ir.VoidType(), [xp.type, up.type, step_k.type, pp.type, op.type])
        builder.call(builder.inttoptr(address, fnty.as_pointer()), [xp, up, step_k, pp, op])
        return context.get_dummy_value()

    return sig, codegen


call_step: Any = intrinsic(_call_step)  # call_step(address, x, u, k, p, out)


KERNEL = Kernel("the compiled-step loop", [Path(__file__)])


@KERNEL.jit
def _apply(step: int, X: Any, U: Any, k: int, P: Any, out: Any) -> None:
    """out[i] = step(X[i], U[i], k, P[i]) for each row (P[0] for every row where P has one row)."""
    last = P.shape[0] - 1
    for i in range(X.shape[0]):
        call_step(step, X[i], U[i], k, P[min(i, last)], out[i])


@KERNEL.jit
def _linearise(step: int, X: Any, U: Any, k0: int, P: Any, A: Any, B: Any, f: Any) -> None:
    """A[j], B[j] = ∂f/∂x, ∂f/∂u and f[j] = f at (X[j], U[j]), step k0 + j, by complex steps: one evaluation of the
    complex128 ``step`` per column with an imaginary perturbation ih, whose imaginary part is h times the column
    (no difference is taken, so the derivative is exact to rounding for any h; h = 1e-30 leaves the real part f)."""
    H, n, m = B.shape
    h = 1e-30
    x = np.empty(n, np.complex128)
    u = np.empty(m, np.complex128)
    p = np.empty(P.shape[0], np.complex128)
    out = np.empty(n, np.complex128)
    p[:] = P
    for j in range(H):
        for c in range(n + m):
            x[:] = X[j]
            u[:] = U[j]
            if c < n:
                x[c] += 1j * h
            else:
                u[c - n] += 1j * h
            call_step(step, x, u, k0 + j, p, out)
            for r in range(n):
                if c < n:
                    A[j, r, c] = out[r].imag / h
                else:
                    B[j, r, c - n] = out[r].imag / h
                if c == 0:
                    f[j, r] = out[r].real


def step_signature(dtype: Any) -> Any:
    """The numba signature of a compiled step: void(x*, u*, intp k, p*, out*), pointers to ``dtype`` (float32 for the
    fused decode kernel, which calls any scenario's step by address through it)."""
    from numba import from_dtype, types

    ptr = types.CPointer(from_dtype(np.dtype(dtype)))
    return types.void(ptr, ptr, types.intp, ptr, ptr)


def _ready(a: np.ndarray, dtype: np.dtype) -> bool:
    """Whether the compiled loop can take ``a`` as it is (its dtype, C-contiguous, writable)."""
    return a.dtype == dtype and a.flags.c_contiguous and a.flags.writeable


def _host(t: Any, dtype: Any) -> np.ndarray:
    """A tensor as a numpy array of ``dtype`` on the CPU (a view where it is one already)."""
    t = t.detach()
    if t.device.type != "cpu" or t.dtype != dtype:
        t = t.to("cpu", dtype)
    return t.contiguous().numpy()


class CompiledStep:
    """A scenario's dynamics as one step function ``func(x, u, k, p, out)`` (the module docstring) and its parameter
    row per problem, ``params(problem)`` (P,) (default: the problem's dt)."""

    def __init__(
        self, func: Callable[..., None], params: Callable[[Problem], Sequence[float] | np.ndarray] | None = None
    ) -> None:
        self.func = func
        self.params = params or (lambda problem: (problem.dt,))
        self._cfuncs: dict[np.dtype, Any] = {}
        self._addresses: dict[np.dtype, int] = {}

    def row(self, problem: Problem) -> np.ndarray:
        """The problem's parameter row p (P,), float64."""
        return np.atleast_1d(np.asarray(self.params(problem), dtype=np.float64))

    def cfunc(self, dtype: Any) -> Any:
        """``func`` compiled for pointers to ``dtype`` (a numba cfunc of ``step_signature``: float64 for the numpy
        step, float32 for the fused decode, complex128 for the Jacobians), once per process."""
        dtype = np.dtype(dtype)
        if dtype not in self._cfuncs:
            kernel = own_file_kernel(f"the dynamics {self.func.__module__}.{self.func.__qualname__}", self.func)
            self._cfuncs[dtype] = kernel.cfunc(self.func, step_signature(dtype))
            self._addresses[dtype] = self._cfuncs[dtype].address
        return self._cfuncs[dtype]

    def address(self, dtype: np.dtype) -> int:
        """The address of ``cfunc(dtype)`` (what ``call_step`` calls)."""
        address = self._addresses.get(dtype)
        if address is None:
            self.cfunc(dtype)
            address = self._addresses[dtype]
        return address

    def apply(self, X: np.ndarray, U: np.ndarray, k: int, P: np.ndarray) -> np.ndarray:
        """The next states of the rows of X (R, n) under U (R, m) at step k with parameter rows P (R or 1, P), in
        X's dtype (float32 or float64; U and P are converted to it)."""
        dtype = np.dtype(X.dtype)
        if dtype not in (np.float32, np.float64):
            raise ValueError(f"compiled dynamics run float32 or float64 states, got {dtype}")
        X, U, P = (a if _ready(a, dtype) else np.require(a, dtype, ["C", "W"]) for a in (X, U, P))
        out = np.empty_like(X)
        _apply(self.address(dtype), X, U, int(k), P, out)
        return out

    def step(self, problem: Problem, k: int, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``Scenario.step``: x_{k+1} in float64, vectorised over the leading axes of x and u."""
        x, u = np.asarray(x, dtype=np.float64), np.asarray(u, dtype=np.float64)
        n, m = x.shape[-1], u.shape[-1]
        lead = x.shape[:-1]
        if u.shape[:-1] != lead:
            lead = np.broadcast_shapes(lead, u.shape[:-1])
            x, u = np.broadcast_to(x, (*lead, n)), np.broadcast_to(u, (*lead, m))
        return self.apply(x.reshape(-1, n), u.reshape(-1, m), k, self.row(problem)[None]).reshape(*lead, n)

    def linearise(self, problem: Problem, window: Window, X_ref: np.ndarray, U_ref: np.ndarray) -> ConvexModel:
        """``Scenario.convex_model``: the first-order Taylor expansion of the step at the reference (H+1, n), (H, m),
        A and B its Jacobians by complex steps (``_linearise``) and c = f(x̄, ū) − A x̄ − B ū, so the model is exact at
        the reference. Dense (no masks)."""
        H = window.length
        X = np.ascontiguousarray(X_ref[:H], dtype=np.float64)
        U = np.ascontiguousarray(U_ref[:H], dtype=np.float64)
        n, m = X.shape[1], U.shape[1]
        A, B, f = np.empty((H, n, n)), np.empty((H, n, m)), np.empty((H, n))
        _linearise(self.address(np.dtype(np.complex128)), X, U, int(window.start), self.row(problem), A, B, f)
        c = f - np.einsum("jab,jb->ja", A, X) - np.einsum("jab,jb->ja", B, U)
        return ConvexModel(A=A, B=B, c=c)

    def batched(self, scenario: Scenario, problems: Sequence[Problem], device: Any = "cpu") -> CompiledBatchedModel:
        """``Scenario.batched_model`` for a scenario whose model representation is its optimisation one."""
        return CompiledBatchedModel(self, scenario, problems, device)


class CompiledBatchedModel:
    """The ``BatchedModel`` of a ``CompiledStep``: ``step`` runs the compiled function over the batch (on the CPU,
    the result moved to the states' device), ``violations`` the scenario's own count per problem, and
    ``fused_step`` gives the decode kernel the float32 function and the problems' parameter rows."""

    def __init__(self, dynamics: CompiledStep, scenario: Scenario, problems: Sequence[Problem], device: Any) -> None:
        self.dynamics, self.scenario, self.problems, self.device = dynamics, scenario, list(problems), device
        rows = np.stack([dynamics.row(p) for p in problems])  # (B, P)
        self.rows = {np.dtype(t): np.ascontiguousarray(rows, dtype=t) for t in (np.float32, np.float64)}

    def step(self, S: Any, A: Any, k: int) -> Any:
        import torch

        X, U = (_host(t, S.dtype) for t in (S, A))
        out = torch.from_numpy(self.dynamics.apply(X, U, k, self.rows.get(X.dtype, X)))
        return out if S.device.type == "cpu" else out.to(S.device)

    def violations(self, S: Any, k: int) -> Any:
        """The scenario's ``violations`` of each problem's state (B,), in S's dtype and device (one call per problem:
        a scenario may override it with a batched count)."""
        import torch

        X = S.detach().to("cpu", torch.float64).numpy()
        sc = self.scenario
        counts = [
            sc.violations(p, sc.from_model_states(p, x[None], start=k), start=k)[0]
            for p, x in zip(self.problems, X, strict=True)
        ]
        return torch.as_tensor(np.asarray(counts), dtype=S.dtype, device=S.device)

    def fused_step(self) -> tuple[Any, np.ndarray]:
        """``BatchedModel.fused_step``: the float32 compiled function and the parameter rows (B, P)."""
        return self.dynamics.cfunc(np.float32), self.rows[np.dtype(np.float32)]


class CompiledScenario(Scenario):
    """A ``Scenario`` whose dynamics are written once, as ``dynamics`` (a ``CompiledStep``): ``step`` and
    ``batched_model`` (its model representation must be the optimisation one) come from it, and with them the fused
    decoder. A subclass may still override either (a vectorised numpy ``step``, a batched ``violations``):
    ``check-scenario`` checks every form against ``step``."""

    dynamics: ClassVar[CompiledStep]

    def step(self, problem: Problem, k: int, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return self.dynamics.step(problem, k, x, u)

    def batched_model(self, problems: Sequence[Problem], device: Any = "cpu") -> CompiledBatchedModel:
        return self.dynamics.batched(self, problems, device)

    def convex_model(self, problem: Problem, window: Window, X_ref: np.ndarray, U_ref: np.ndarray) -> ConvexModel:
        return self.dynamics.linearise(problem, window, X_ref, U_ref)
