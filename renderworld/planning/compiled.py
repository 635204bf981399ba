"""Which exceptions mean "``torch.compile`` could not compile", as opposed to a fault of the code.

The planner's compiled decoder falls back to eager mode only on these: a missing or broken C++
compiler, a missing Triton, an operator the backend cannot lower, a construct Dynamo does not
trace. Every other exception of a compiled call (out of memory, a shape bug surfacing while
tracing as ``TorchRuntimeError``, a CUDA fault) is the caller's to see, raised as is, and so is
a backend failure whose cause is running out of memory (autotuning on a full GPU).
"""

from __future__ import annotations

__all__ = ["compile_failures", "is_compile_failure"]


def compile_failures() -> tuple[type[BaseException], ...]:
    """The exception types of a failed compilation (imported on use: ``torch._dynamo`` is heavy).

    Returns:
        ``torch._dynamo.exc``: ``BackendCompilerFailed`` (what Inductor's errors arrive as,
        ``InductorError`` included), ``Unsupported``, ``InternalTorchDynamoError``,
        ``InvalidBackend``; ``torch._inductor.exc``: ``CppCompileError`` (and
        ``CUDACompileError``), ``InvalidCxxCompiler``, ``OperatorIssue`` (lowering errors),
        ``TritonMissing``, ``GPUTooOldForTriton``.
    """
    from torch._dynamo import exc as dynamo
    from torch._inductor import exc as inductor

    return (
        dynamo.BackendCompilerFailed,
        dynamo.Unsupported,
        dynamo.InternalTorchDynamoError,
        dynamo.InvalidBackend,
        inductor.CppCompileError,
        inductor.InvalidCxxCompiler,
        inductor.OperatorIssue,
        inductor.TritonMissing,
        inductor.GPUTooOldForTriton,
    )


def is_compile_failure(err: BaseException) -> bool:
    """Whether ``err`` says the code could not be compiled (see :func:`compile_failures`).

    Args:
        err: an exception raised by a ``torch.compile``-d callable.

    Returns:
        True for the compile failures, except a backend failure caused by out of memory.
    """
    import torch

    if not isinstance(err, compile_failures()):
        return False
    inner = getattr(err, "inner_exception", None)
    return not isinstance(inner, torch.OutOfMemoryError)
