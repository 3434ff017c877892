"""`compile_processor`: `torch.compile` of a simulator's message-passing blocks in place (the
`ggns.callbacks.CompileProcessor` callback and the benchmarks call it; docs/speed.md measures it)."""
from __future__ import annotations


def compile_processor(model, backend: str = "inductor", mode: str | None = None, dynamic: bool = True) -> None:
    """Compile `model.core.processor`'s blocks in place (see `CompileProcessor`)."""
    for block in model.core.processor:
        block.compile(backend=backend, mode=mode, dynamic=dynamic)
