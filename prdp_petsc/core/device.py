"""Vectors and matrix values that PETSc shares with the caller's memory, by DLPack.

A `KSPSolver` whose options name a ``vec_type`` or ``mat_type`` (with its prefix, or
on the command line: ``-fwd_vec_type cuda -fwd_mat_type aijcusparse``) runs on the
*device path*: its Mats are of that type, and the right-hand sides and solutions are
the caller's own arrays, wrapped by DLPack (``VecCreateWithDLPack``: the Vec's array
is the caller's memory, host or GPU), so no vector is copied in either direction.
Any array with ``__dlpack__`` is taken (torch, CuPy, JAX, numpy); nothing here
imports torch.  What crosses to the host per call is a few scalars: norms, iteration
counts, reasons.

`DeviceTypes` resolves the two option values into the types PETSc is given and the
memory they live in (``"cpu"`` or ``"cuda"``); `wrap` makes a Vec of an array;
`set_values_coo` sets a Mat's values from an array in the Mat's own memory
(``MatSetValuesCOO`` through ctypes: petsc4py's ``Mat.setValuesCOO`` takes host
arrays only, PETSc's C function device pointers too).

Decisions, and why:

* Only the forward options carry the types (the adjoint solves with the same Mat and
  Vecs); ``vec_type`` / ``mat_type`` among `AdjointSettings` options are refused.
* The pairs PETSc runs without copies are accepted: host (``standard``/``seq``/``mpi``
  with ``aij``/``seqaij``/``mpiaij``) and CUDA (``cuda``/``seqcuda``/``mpicuda`` with
  ``aijcusparse``/...).  One named alone implies its partner; a host Vec with a CUDA
  Mat (or the reverse) is refused rather than run with a copy at every product.  CUDA
  types need a PETSc built with CUDA (``PETSc.Sys.hasExternalPackage("cuda")``).
* A freshly wrapped Vec has object state 0, where PETSc's norm cache reads the
  never-computed norms of every other type as valid zeros (after ``‖v‖₂``,
  ``‖v‖_∞`` returns 0.0): `wrap` increases its state once, so every norm is computed.
* petsc4py's ``createWithDLPack`` ignores strides (a non-contiguous view would wrap
  the wrong entries), so `wrap` refuses any array that is not C-contiguous.
"""

from __future__ import annotations

import ctypes
import functools
import math
from dataclasses import dataclass

from petsc4py import PETSc

from ..errors import InputError, NonFiniteError

__all__ = [
    "DeviceTypes",
    "WrappedRows",
    "dlpack_memory",
    "libpetsc",
    "nonfinite",
    "set_values_coo",
    "wrap",
]

#: Vec and Mat type names by the memory they keep their entries in
_VEC_TYPES = {
    "cpu": ("standard", "seq", "mpi"),
    "cuda": ("cuda", "seqcuda", "mpicuda"),
}
_MAT_TYPES = {
    "cpu": ("aij", "seqaij", "mpiaij"),
    "cuda": ("aijcusparse", "seqaijcusparse", "mpiaijcusparse"),
}
#: DLPack device codes (``__dlpack_device__()[0]``): kDLCPU, kDLCUDA, kDLCUDAHost, kDLCUDAManaged
_DLPACK_MEMORY = {1: "cpu", 2: "cuda", 3: "cpu", 13: "cuda"}
_INSERT_VALUES = 1  # PETSc's InsertMode INSERT_VALUES


@dataclass(frozen=True)
class DeviceTypes:
    """The Vec and Mat types of a solver on the device path, and their memory.

    Attributes
    ----------
    vec_type, mat_type : str
        PETSc type names, as given or implied by the other.
    memory : {"cpu", "cuda"}
        Where the entries live: the memory every array given to the solver must be in.
    """

    vec_type: str
    mat_type: str
    memory: str

    @classmethod
    def resolve(cls, vec_type: str | None, mat_type: str | None) -> DeviceTypes | None:
        """The types named by the options (None: neither was, the default path).

        Raises `InputError` for a type outside the supported pairs, a pair in two
        memories, or CUDA types with a PETSc built without CUDA.
        """
        if vec_type is None and mat_type is None:
            return None
        vec_memory = _memory_of(vec_type, _VEC_TYPES, "vec_type")
        mat_memory = _memory_of(mat_type, _MAT_TYPES, "mat_type")
        if vec_memory and mat_memory and vec_memory != mat_memory:
            raise InputError(
                f"vec_type {vec_type} keeps vectors in {vec_memory} memory and mat_type "
                f"{mat_type} the matrix in {mat_memory} memory: every product would copy. "
                "Name a pair in one memory (standard with aij, cuda with aijcusparse)"
            )
        memory = vec_memory or mat_memory
        if memory == "cuda" and not PETSc.Sys.hasExternalPackage("cuda"):
            raise InputError(
                f"vec_type {vec_type or 'cuda'} / mat_type {mat_type or 'aijcusparse'} need a "
                "PETSc built with CUDA, and this one is not (PETSc.Sys.hasExternalPackage"
                "('cuda') is False): build PETSc with --with-cuda, or drop the types to solve "
                "on the host"
            )
        return cls(
            vec_type if vec_type is not None else _VEC_TYPES[memory][0],
            mat_type if mat_type is not None else _MAT_TYPES[memory][0],
            memory,
        )


def _memory_of(name: str | None, table: dict, option: str) -> str | None:
    if name is None:
        return None
    for memory, names in table.items():
        if name in names:
            return memory
    known = ", ".join(n for names in table.values() for n in names)
    raise InputError(f"{option} {name}: the device path takes {known}")


def dlpack_memory(array) -> str:
    """``"cpu"`` or ``"cuda"``: where `array` (any object with ``__dlpack__``) keeps its
    entries, from its ``__dlpack_device__``; `InputError` for another memory."""
    device = getattr(array, "__dlpack_device__", None)
    if device is None or not hasattr(array, "__dlpack__"):
        raise InputError(
            f"a solver with vec_type/mat_type options takes arrays with __dlpack__ (torch, "
            f"CuPy, JAX, numpy), got {type(array).__name__}"
        )
    code = int(device()[0])
    if code not in _DLPACK_MEMORY:
        raise InputError(f"DLPack device type {code}: PETSc wraps host and CUDA memory only")
    return _DLPACK_MEMORY[code]


def wrap(array, size: int, name: str, memory: str) -> PETSc.Vec:
    """A sequential Vec whose array is `array`'s memory (no copy), checked.

    `array` is a C-contiguous float64 array with ``__dlpack__`` of `size` entries in
    `memory`; `name` says what it is in an error.  The Vec keeps a reference to the
    array (petsc4py's ``createWithDLPack`` releases the DLPack capsule's own at once,
    so without it a temporary array's memory would be freed under the Vec).
    """
    where = dlpack_memory(array)
    if where != memory:
        raise InputError(
            f"{name} is in {where} memory, the solver's types (vec_type/mat_type options) "
            f"in {memory} memory: "
            + (
                "move it to the GPU (.cuda()) or give the solver host types"
                if memory == "cuda"
                else "move it to the host (.cpu()) or give the solver CUDA types "
                "(vec_type cuda, mat_type aijcusparse)"
            )
        )
    try:
        vec = PETSc.Vec().createWithDLPack(array, comm=PETSc.COMM_SELF)
    except TypeError as err:  # the dtype
        raise TypeError(f"{name} must be float64: {err}") from err
    context = vec.getAttr("__dltensor_ctx__")
    if context is not None:
        ndim, shape, strides = context[2], list(context[3]), list(context[4])
        expected = [1] * ndim
        for i in range(ndim - 2, -1, -1):
            expected[i] = expected[i + 1] * shape[i + 1]
        if any(s != e for s, e, n in zip(strides, expected, shape, strict=True) if n > 1):
            vec.destroy()
            raise InputError(f"{name} must be C-contiguous (PETSc wraps its memory as it lies)")
    if vec.getSize() != size:
        n = vec.getSize()
        vec.destroy()
        raise InputError(f"{name} has {n} entries, the operator {size}")
    vec.stateIncrease()  # state 0 would make PETSc's cache report unknown norms as 0.0
    vec.setAttr("__wrapped__", array)  # petsc4py frees the DLPack manager at once
    return vec


@functools.cache
def libpetsc() -> ctypes.CDLL:
    """The PETSc library petsc4py runs on, for C functions petsc4py does not wrap: the
    ``libpetsc`` mapped into this process (``/proc/self/maps``), else the one in
    ``petsc4py.get_config()``'s ``PETSC_DIR/PETSC_ARCH/lib``."""
    paths = []
    try:
        with open("/proc/self/maps") as maps:
            paths = sorted({line.split()[-1] for line in maps if "/libpetsc." in line})
    except OSError:
        pass
    if not paths:
        import os

        import petsc4py

        config = petsc4py.get_config()
        paths = [os.path.join(config["PETSC_DIR"], config["PETSC_ARCH"], "lib", "libpetsc.so")]
    lib = ctypes.CDLL(paths[0])
    lib.MatSetValuesCOO.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int]
    lib.MatSetValuesCOO.restype = ctypes.c_int
    return lib


def nonfinite(vec: PETSc.Vec) -> bool:
    """Whether `vec` has a NaN or Inf entry, from ``‖v‖₁`` (a sum, which every NaN and
    Inf reaches, where a maximum's comparisons may pass over a NaN) and, only where that
    is infinite (an Inf, or an overflow of large finite entries), ``‖v‖_∞``.  Two
    scalars cross to the host at most."""
    total = vec.norm(PETSc.NormType.NORM_1)
    if math.isnan(total):
        return True
    return math.isinf(total) and not math.isfinite(vec.norm(PETSc.NormType.INFINITY))


def set_values_coo(mat: PETSc.Mat, values: PETSc.Vec) -> None:
    """``MatSetValuesCOO(mat, values, INSERT_VALUES)`` from the array of Vec `values` as it
    lies: the device pointer of a CUDA Vec, the host pointer otherwise (PETSc checks the
    memory type and copies within the device).  The pattern was set by
    ``mat.setPreallocationCOO`` in the same order as `values`."""
    if values.getType() in _VEC_TYPES["cuda"]:
        pointer = values.getCUDAHandle("r")
        try:
            code = libpetsc().MatSetValuesCOO(mat.handle, pointer, _INSERT_VALUES)
        finally:
            values.restoreCUDAHandle(pointer, "r")
    else:
        pointer = values.getArray(readonly=True).ctypes.data
        code = libpetsc().MatSetValuesCOO(mat.handle, pointer, _INSERT_VALUES)
    if code:
        raise RuntimeError(f"MatSetValuesCOO failed with PETSc error code {code}")


class WrappedRows:
    """The rows of one device-path call (`KSPSolver.solve` with ``out=``): each right-hand
    side and each solution row wrapped as a Vec (`wrap`), checked, freed by `destroy`.

    Parameters
    ----------
    rhs, out : array with ``__dlpack__``, or a sequence of them
        One row ``(n,)``, or the rows of a batch; `out` receives the solutions (it must
        not share memory with `rhs`).
    size : int
        Entries of a row (the operator's).
    memory : {"cpu", "cuda"}
        Memory of the solver's types; every array must be in it.
    kind : Side
        Which solve, named in errors.
    value : optional
        What `value` returns (default `out`): the array whose rows `out` lists.

    Notes
    -----
    NaN or Inf in a right-hand side is refused (`NonFiniteError`) before any row is
    solved, and in a solution found once every row is (`finite`), each by `nonfinite`:
    one or two PETSc norms per row, where they live.
    """

    def __init__(self, rhs, out, size: int, memory: str, kind, value=None) -> None:
        what = "cotangent" if kind.value == "adjoint" else "right-hand side"
        if out is None:
            raise InputError(
                "a solver with vec_type/mat_type options writes the solution into memory the "
                "caller gives: solve(b, out=x), x an array like b"
            )
        rhs_rows = [rhs] if hasattr(rhs, "__dlpack__") else list(rhs)
        out_rows = [out] if hasattr(out, "__dlpack__") else list(out)
        if len(rhs_rows) != len(out_rows) or not rhs_rows:
            raise InputError(
                f"out= must hold one row per row of the {what}: {len(out_rows)} for {len(rhs_rows)}"
            )
        self.b: list[PETSc.Vec] = []
        self.x: list[PETSc.Vec] = []
        self._out = out if value is None else value
        try:
            for i, (row, target) in enumerate(zip(rhs_rows, out_rows, strict=True)):
                name = what if len(rhs_rows) == 1 else f"row {i} of the {what}"
                hint = f"the {name} (a batch is a sequence of rows)"
                self.b.append(wrap(row, size, hint, memory))
                self.x.append(wrap(target, size, f"out ({name})", memory))
            self._check_finite(kind, what)
        except BaseException:
            self.destroy()
            raise

    def _check_finite(self, kind, what: str) -> None:
        bad = [i for i, vec in enumerate(self.b) if nonfinite(vec)]
        if bad:
            where = f" (rows {bad[:5]}{', ...' if len(bad) > 5 else ''})" if len(self.b) > 1 else ""
            raise NonFiniteError(f"{kind} solve: the {what} contains NaN or Inf{where}")

    def __len__(self) -> int:
        return len(self.b)

    def solve(self, step, i: int) -> int:
        """Row `i` through `step` (`SolveStep.solve_vecs`); the iterations it ran."""
        return step.solve_vecs(self.b[i], self.x[i])

    def finite(self) -> bool:
        """Whether every solution row is finite (`nonfinite` of each)."""
        return not any(nonfinite(vec) for vec in self.x)

    def value(self):
        """`out` as the caller gave it (or the `value` given)."""
        return self._out

    def destroy(self) -> None:
        """Free the Vecs (the arrays are the caller's, untouched)."""
        for vec in (*self.b, *self.x):
            vec.destroy()
        self.b, self.x = [], []
