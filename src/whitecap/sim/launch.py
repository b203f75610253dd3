"""The solver's kernel launches, written once and run either directly or as a
Taichi compute graph (``ti.graph``).

Why a graph: Taichi 1.7.4 spends its launch time in Python, setting each
argument (about 150 µs a launch for a kernel of three arguments, 250 µs for
the obstacle kernels' twenty, measured on the 2-core development machine at
n = 0). A step of the solver launches 22 kernels, 29 with an obstacle, so at
15k particles a fifth of a step went to launching. A compute graph binds its
arguments once per run and launches its kernels from C++ (about 45–70 µs each,
most of it the thread pool's dispatch).

A sequence of launches is a function of a *recorder*: ``rec(kernel, *args)``
launches ``kernel``, where every argument that is not a compile-time template
is a :class:`Ref`, ``rec["name"]``, naming an entry of the *bindings* (a dict
of ndarrays, scalars and vectors given at run time). :class:`DirectRecorder`
launches at once; :class:`GraphRecorder` builds a graph that
:class:`KernelGraph` compiles once and runs with new bindings each time.

Ping-pong buffers are *roles*: ``rec.swap("p", "t")`` makes later ``rec["p"]``
name the binding that ``rec["t"]`` named. Both recorders track roles the same
way; :attr:`Recorder.roles` after a sequence says which binding ended in which
role, and the caller permutes its arrays alike (:func:`permuted`).

Template arguments (compile-time values such as a loop bound) are passed as
plain Python values in both modes: :class:`GraphRecorder` compiles the kernel
with them, which ``ti.graph.GraphBuilder.dispatch`` itself does not support in
Taichi 1.7.4 (it takes every argument as a symbolic graph argument)."""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import taichi as ti
from taichi.aot.utils import produce_injected_args
from taichi.lang.matrix import MatrixType
from taichi.types.annotations import Template
from taichi.types.ndarray_type import NdarrayType

#: A kernel argument fixed at compile time, ``ti.template()`` (typed Any: Taichi's annotations are not
#: Python types), for the kernels' signatures.
TEMPLATE: Any = ti.template()


class Ref(NamedTuple):
    """A kernel argument given at run time: the bindings' entry ``name``."""

    name: str


class Recorder:
    """Role tracking shared by both ways of launching."""

    def __init__(self) -> None:
        self.roles: dict[str, str] = {}

    def __getitem__(self, name: str) -> Ref:
        return Ref(self.roles.get(name, name))

    def swap(self, a: str, b: str) -> None:
        """Ping-pong: from now on role ``a`` is what ``b`` was and the other way round."""
        ra, rb = self[a].name, self[b].name
        self.roles[a], self.roles[b] = rb, ra
        for k in (a, b):  # a role back on its own binding needs no permutation
            if self.roles[k] == k:
                del self.roles[k]

    def __call__(self, kernel, *args) -> None:  # pragma: no cover - interface
        raise NotImplementedError


class DirectRecorder(Recorder):
    """Launches every kernel at once, its arguments looked up in ``bindings``."""

    def __init__(self, bindings: dict) -> None:
        super().__init__()
        self.bindings = bindings

    def __call__(self, kernel, *args) -> None:
        kernel(*[self.bindings[a.name] if isinstance(a, Ref) else a for a in args])


class _Shim:
    """Stands in for a kernel whose template parameters have been taken out."""

    def __init__(self, arguments) -> None:
        self.arguments = arguments


def _graph_arg(name: str, annotation):
    """The ``ti.graph.Arg`` that a kernel parameter with this annotation takes."""
    kind = ti.graph.ArgKind
    if isinstance(annotation, NdarrayType):
        return ti.graph.Arg(kind.NDARRAY, name, annotation.dtype, ndim=annotation.ndim)
    if isinstance(annotation, MatrixType):
        return ti.graph.Arg(kind.MATRIX, name, annotation)
    return ti.graph.Arg(kind.SCALAR, name, annotation)


class GraphRecorder(Recorder):
    """Adds every launch to a ``ti.graph.GraphBuilder``."""

    def __init__(self) -> None:
        super().__init__()
        self.builder = ti.graph.GraphBuilder()
        self.args: dict[str, object] = {}  # binding name -> its graph argument, made at first use

    def __call__(self, kernel, *args) -> None:
        primal = kernel._primal
        params = primal.arguments
        if len(args) != len(params):
            raise TypeError(f"{primal.func.__name__} takes {len(params)} arguments, got {len(args)}")
        symbolic, kept = [], []
        for a, p in zip(args, params):
            if isinstance(p.annotation, Template):
                continue
            if not isinstance(a, Ref):
                raise TypeError(f"{primal.func.__name__}: argument {p.name} must be a Ref in a graph, got {a!r}")
            if a.name not in self.args:
                self.args[a.name] = _graph_arg(a.name, p.annotation)
            symbolic.append(self.args[a.name])
            kept.append(p)
        # Compile the kernel for this call's template values (dummies stand in for the rest),
        # then add the compiled kernel with its symbolic arguments.
        dummies = iter(produce_injected_args(_Shim(kept), symbolic_args=symbolic))
        injected = [a if isinstance(p.annotation, Template) else next(dummies) for a, p in zip(args, params)]
        key = primal.ensure_compiled(*injected)
        self.builder._graph_builder.dispatch(primal.compiled_kernels[key], symbolic)


class KernelGraph:
    """A sequence of launches, ``record(rec)``, compiled into a graph on first use.

    ``run(bindings)`` launches the sequence with these bindings and returns the
    roles it ended with (see :class:`Recorder`)."""

    def __init__(self, record: Callable[[Recorder], None]) -> None:
        rec = GraphRecorder()
        record(rec)
        self.roles = dict(rec.roles)
        self.names = tuple(rec.args)
        self.graph = rec.builder.compile()

    def run(self, bindings: dict) -> dict[str, str]:
        self.graph.run({k: bindings[k] for k in self.names})
        return self.roles


def run_direct(record: Callable[[Recorder], None], bindings: dict) -> dict[str, str]:
    """The same sequence launched kernel by kernel; returns the roles it ended with."""
    rec = DirectRecorder(bindings)
    record(rec)
    return rec.roles


def permuted(values: dict, roles: dict[str, str]) -> dict:
    """``values`` after a sequence that ended with ``roles``: each role takes the value
    of the binding it ended on."""
    return {k: values[roles.get(k, k)] for k in values}
