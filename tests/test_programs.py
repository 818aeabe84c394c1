"""Ahead-of-time compiled programs (physics.programs): both call paths equal the traced function and refuse
inputs of other shapes."""
import pytest
import torch

from physics.programs import compile_program


MODES = {"wrapped": {}, "jit": {"direct": True, "ahead_of_time": False}, "aot": {"direct": True}}


@pytest.mark.parametrize("mode", MODES)
def test_program_equals_its_function_for_tensor_and_tuple_outputs_and_checks_shapes(mode):
    torch.manual_seed(0)
    x, w = torch.randn(5, 4), torch.randn(4, 3)
    one = lambda x, w: torch.tanh(x @ w) + 1  # noqa: E731
    two = lambda x, w: (x + w.sum(), torch.sigmoid(x @ w))  # noqa: E731
    p_one, p_two = compile_program(one, [x, w], **MODES[mode]), compile_program(two, [x, w], **MODES[mode])
    for _ in range(2):  # new inputs of the same shapes, not the traced ones
        x, w = torch.randn(5, 4), torch.randn(4, 3)
        got = p_one(x, w)
        assert isinstance(got, torch.Tensor) and torch.allclose(got, one(x, w), atol=1e-6)
        a, b = p_two(x, w)
        assert torch.allclose(a, two(x, w)[0], atol=1e-6) and torch.allclose(b, two(x, w)[1], atol=1e-6)
    with pytest.raises(RuntimeError, match="expected size 6==5|expected: 5, but got: 6"):  # JIT | AOT wrapper
        p_one(torch.randn(6, 4), w)
    with pytest.raises(RuntimeError, match="stride"):
        p_one(torch.randn(4, 5).t(), w)


def test_a_direct_cpu_program_holds_the_tensors_its_function_holds():
    """A direct program on the CPU (ahead of time, its constants inside it) computes with the tensors the function
    holds (weights become the program's constants), for new inputs, with tuple outputs, each in its own storage."""
    torch.manual_seed(1)
    W, b, v = torch.randn(4, 6), torch.randn(6), torch.randn(6, 2)
    fn = lambda x: (torch.tanh(x @ W + b), torch.sigmoid(x @ W) @ v)  # noqa: E731
    prog = compile_program(fn, [torch.randn(5, 4)], gemm_templates=True, direct=True)
    for _ in range(2):
        x = torch.randn(5, 4)
        for got, want in zip(prog(x), fn(x)):
            assert torch.allclose(got, want, atol=1e-6)
            # its own storage: an output kept (a rollout's frames) keeps none of the call's other buffers
            assert got.untyped_storage().nbytes() == got.numel() * got.element_size()


@pytest.mark.parametrize("mode", MODES)
def test_a_program_traced_with_one_tensor_as_two_inputs_keeps_them_apart(mode):
    """One tensor passed as two inputs while tracing (zeros for both a force and an offset) is traced as two: later
    calls with different tensors read each where it is used (before 2026-11-30 one input stood for both)."""
    zero = torch.zeros(3)
    prog = compile_program(lambda a, b: 2 * a - b, [zero, zero], **MODES[mode])
    a, b = torch.tensor([1.0, 2.0, 3.0]), torch.tensor([0.5, 0.0, -1.0])
    assert torch.equal(prog(a, b), 2 * a - b)


@pytest.mark.parametrize("mode", ["jit", "aot"])
def test_fast_exp_is_its_own_program_and_accurate_to_a_few_units_in_the_last_place(mode):
    """``fast_exp`` (ATen's inline ``exp_u20``) against Sleef's: within 6e-7 (Sleef's 1.5e-7) of float64 over the
    range sigmoids see (measured 3.7e-7 and 7.6e-8); a sigmoid still 0 and 1 at -inf and inf; and a program of its
    own: compiled after the same graph with Sleef's ``exp`` (ahead of time, inductor names a library for its wrapper
    code, the same for both), its results differ."""
    x = torch.linspace(-80.0, 80.0, 10_001)  # not a multiple of the vector width: the tail too
    x[0], x[5000], x[-1] = -float("inf"), 0.0, float("inf")
    fn = lambda a: (torch.exp(a), 1 / (1 + torch.exp(-a)))  # noqa: E731
    ref = torch.exp(x[1:-1].double())  # exp(0) = 1 exactly in both
    got = {}
    for fast in (False, True):
        got[fast], sig = compile_program(fn, [x], **MODES[mode], fast_exp=fast)(x)
        assert float(((got[fast][1:-1].double() - ref) / ref).abs().max()) < (6e-7 if fast else 1.5e-7)
        assert sig[[0, -1, 5000]].tolist() == [0.0, 1.0, 0.5]
    assert not torch.equal(got[False], got[True])


@pytest.mark.parametrize("mode", MODES)
def test_programs_that_differ_only_in_their_constants_compute_with_their_own(mode):
    """Two functions of one graph holding different tensors (two models of one architecture, two LGVIs of one rod
    under different forces) compile to two programs, each with its own constants, in one process. Ahead of time
    inductor names a library for its wrapper code, which is the same for both, and a library loaded twice from one
    path is the first one: before 2026-12-02 the second program returned the first one's results."""
    def scaled(c):
        return lambda x: torch.exp(x * c) + c

    x = torch.linspace(-1.0, 1.0, 7)
    for c in (torch.full((7,), 0.5), torch.full((7,), -2.0), torch.full((7,), 0.5)):
        assert torch.allclose(compile_program(scaled(c), [x], **MODES[mode])(x), scaled(c)(x), atol=1e-6)


@pytest.mark.parametrize("mode", MODES)
def test_a_scalar_program_equals_the_vectorised_one_on_trailing_three_vectors(mode):
    """``vectorize=False`` (inductor's C++ kernels as scalar loops; the LGVI's step, whose innermost dimension is a
    3-vector) is accepted on every call path and computes what the vectorised program and the function do, for a
    batch that is not a multiple of any vector width."""
    torch.manual_seed(1)
    a, b = torch.randn(37, 11, 3, dtype=torch.float64), torch.randn(37, 11, 3, dtype=torch.float64)
    fn = lambda a, b: torch.linalg.cross(a, b, dim=-1) / (1 + (a * b).sum(-1, keepdim=True) ** 2)  # noqa: E731
    want = fn(a, b)
    for vec in (True, False):
        got = compile_program(fn, [a, b], **MODES[mode], vectorize=vec)(a, b)
        assert torch.allclose(got, want, rtol=0, atol=1e-14)


def test_an_ahead_of_time_library_is_built_once_and_loaded_by_later_programs(monkeypatch):
    """A second program of the same graph, constants and inputs' layout loads the library built for the first (each
    built its own before: about half a minute for the LGVI's four steps); GEMM templates build another (other constants
    do: test_programs_that_differ_only_in_their_constants_compute_with_their_own)."""
    import time

    import torch._inductor
    builds, build = [], torch._inductor.aot_compile
    monkeypatch.setattr(torch._inductor, "aot_compile", lambda *a, **k: builds.append(1) or build(*a, **k))
    x = torch.randn(5, 4)
    W = torch.randn(4, 3) * (1 + time.time_ns() % 10**9 * 1e-12)  # constants no earlier run built a library for
    first = compile_program(lambda x: torch.tanh(x @ W), [x], direct=True)
    again = compile_program(lambda x: torch.tanh(x @ W), [x], direct=True)
    assert len(builds) == 1 and torch.equal(first(x), again(x)) and torch.allclose(again(x), torch.tanh(x @ W))
    templated = compile_program(lambda x: torch.tanh(x @ W), [x], direct=True, gemm_templates=True)
    assert len(builds) == 2 and torch.allclose(templated(x), torch.tanh(x @ W), atol=1e-6)
