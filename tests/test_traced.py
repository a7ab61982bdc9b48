"""The trace cache: a shape's first calls run the module, later ones its trace, with the same numbers."""

from __future__ import annotations

import pickle

import torch as th

from sb3_gccp.traced import TRACE_AFTER_CALLS, TraceCache


class Counted(th.nn.Module):
    """A linear layer that counts the calls of its Python forward (a trace does not call it)."""

    def __init__(self) -> None:
        super().__init__()
        self.linear = th.nn.Linear(3, 2)
        self.calls = 0

    def forward(self, obs: dict[str, th.Tensor]) -> th.Tensor:
        self.calls += 1
        return self.linear(obs["x"]).tanh()


def test_a_shape_is_traced_after_its_first_calls_and_gives_the_modules_numbers():
    th.manual_seed(0)
    module = Counted()
    cache = TraceCache(module, after_calls=2)
    batches = [{"x": th.randn(4, 3)} for _ in range(5)]
    with th.no_grad():
        outputs = [cache(obs) for obs in batches]
        assert module.calls == 3  # two calls, then one more while tracing, none after
        assert len(cache._traced) == 1
        for out, obs in zip(outputs, batches, strict=True):
            assert th.equal(out, module.linear(obs["x"]).tanh())
        cache({"x": th.randn(2, 3)})  # another shape counts its own calls
        assert module.calls == 4 and len(cache._traced) == 1
        module.linear.weight.add_(1.0)  # trained in place: the trace sees the new weights
        assert th.equal(cache(batches[0]), module.linear(batches[0]["x"]).tanh())


def test_a_pickled_cache_keeps_its_threshold_and_traces_its_own():
    cache = TraceCache(Counted(), after_calls=0)
    with th.no_grad():
        cache({"x": th.randn(1, 3)})
    copy = pickle.loads(pickle.dumps(cache))
    assert cache._traced and not copy._traced and copy.after_calls == 0
    assert TraceCache(Counted()).after_calls == TRACE_AFTER_CALLS
