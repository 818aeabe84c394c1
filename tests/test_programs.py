"""Ahead-of-time compiled programs (physics.programs): both call paths equal the traced function and refuse
inputs of other shapes."""
import pytest
import torch

from physics.programs import compile_program


@pytest.mark.parametrize("direct", [False, True])
def test_program_equals_its_function_for_tensor_and_tuple_outputs_and_checks_shapes(direct):
    torch.manual_seed(0)
    x, w = torch.randn(5, 4), torch.randn(4, 3)
    one = lambda x, w: torch.tanh(x @ w) + 1  # noqa: E731
    two = lambda x, w: (x + w.sum(), torch.sigmoid(x @ w))  # noqa: E731
    p_one, p_two = compile_program(one, [x, w], direct=direct), compile_program(two, [x, w], direct=direct)
    for _ in range(2):  # new inputs of the same shapes, not the traced ones
        x, w = torch.randn(5, 4), torch.randn(4, 3)
        got = p_one(x, w)
        assert isinstance(got, torch.Tensor) and torch.allclose(got, one(x, w), atol=1e-6)
        a, b = p_two(x, w)
        assert torch.allclose(a, two(x, w)[0], atol=1e-6) and torch.allclose(b, two(x, w)[1], atol=1e-6)
    with pytest.raises(RuntimeError, match="expected size 6==5"):
        p_one(torch.randn(6, 4), w)


@pytest.mark.parametrize("direct", [False, True])
def test_a_program_traced_with_one_tensor_as_two_inputs_keeps_them_apart(direct):
    """One tensor passed as two inputs while tracing (zeros for both a force and an offset) is traced as two: later
    calls with different tensors read each where it is used (before 2026-11-30 one input stood for both)."""
    zero = torch.zeros(3)
    prog = compile_program(lambda a, b: 2 * a - b, [zero, zero], direct=direct)
    a, b = torch.tensor([1.0, 2.0, 3.0]), torch.tensor([0.5, 0.0, -1.0])
    assert torch.equal(prog(a, b), 2 * a - b)
