"""The small batched products of the step (`spatial.small_matmul`, `small_matvec`): the broadcast
form a GPU runs gives ``@``'s values and gradients at every shape the simulator multiplies, here
on the CPU in float64 (the CPU itself keeps ``@``, bit for bit). And the solves of symmetric
positive definite matrices (`spatial.solve_spd`): the CPU's Cholesky form gives the general
solve's values and gradients, and an env whose matrix is not positive definite gets NaN alone."""
import pytest
import torch

from torchrl_diffenvs.articulated.spatial import small_matmul, small_matvec, solve_spd

N = 3
# (left, right) of each call site: the batch dimensions broadcast as ``@``'s do
MATRIX_PRODUCTS = [
    ((N, 5, 3, 3), (5, 3, 3)),  # a body's rotation times the model's geom or body frames
    ((N, 5, 3, 3), (N, 5, 3, 3)),  # rotations times rotations (the joints' chain), inertias
    ((1, 5, 3, 3), (N, 5, 3, 3)),  # the model's inertia for every env
    ((1, 4, 6), (N, 6, 4)),  # motion axes times momenta (the composite mass matrix)
    ((N, 12, 6), (N, 6, 4)),  # contact-frame row blocks times the dofs' motion axes
]
MATRIX_VECTOR_PRODUCTS = [
    ((N, 5, 3, 3), (5, 3)),  # a body's rotation times the model's offsets
    ((N, 4, 6, 6), (N, 4, 6)),  # composite inertias times motion axes
    ((N, 4, 6, 6), (1, 4, 6)),
    ((N, 2, 4, 7), (N, 1, 7)),  # a contact's pyramid edges times the joint velocities
]


@pytest.mark.parametrize("left,right", MATRIX_PRODUCTS)
def test_the_broadcast_product_is_matmul(left, right):
    gen = torch.Generator().manual_seed(0)
    a, b = (torch.randn(*shape, generator=gen, dtype=torch.float64, requires_grad=True) for shape in (left, right))
    torch.testing.assert_close(small_matmul(a, b, broadcast=True), a @ b, rtol=1e-14, atol=1e-14)
    assert torch.equal(small_matmul(a, b), a @ b)  # the CPU's form
    assert torch.autograd.gradcheck(lambda x, y: small_matmul(x, y, broadcast=True), (a, b))


@pytest.mark.parametrize("left,right", MATRIX_VECTOR_PRODUCTS)
def test_the_broadcast_matrix_vector_product_is_matmul(left, right):
    gen = torch.Generator().manual_seed(1)
    a, v = (torch.randn(*shape, generator=gen, dtype=torch.float64, requires_grad=True) for shape in (left, right))
    expected = (a @ v.unsqueeze(-1)).squeeze(-1)
    torch.testing.assert_close(small_matvec(a, v, broadcast=True), expected, rtol=1e-14, atol=1e-14)
    assert torch.equal(small_matvec(a, v), expected)
    assert torch.autograd.gradcheck(lambda x, y: small_matvec(x, y, broadcast=True), (a, v))


def _spd(factor):
    # symmetric by construction, as the mass matrix and M + J' W J are: a Cholesky factor reads one
    # triangle, so the two solves' gradients agree along symmetric perturbations only
    return factor @ factor.transpose(-1, -2) + factor.shape[-1] * torch.eye(factor.shape[-1], dtype=factor.dtype)


@pytest.mark.parametrize("size", [9, 14, 27])  # HalfCheetah's nv, the Ant's, the humanoids'
def test_the_cholesky_solve_is_the_general_solve(size):
    gen = torch.Generator().manual_seed(size)
    factor = torch.randn(N, size, size, generator=gen, dtype=torch.float64, requires_grad=True)
    rhs = torch.randn(N, size, generator=gen, dtype=torch.float64, requires_grad=True)
    general = torch.linalg.solve_ex(_spd(factor), rhs)[0]
    cholesky = solve_spd(_spd(factor), rhs, by_cholesky=True)
    torch.testing.assert_close(cholesky, general, rtol=1e-12, atol=1e-12)
    weights = torch.randn(N, size, generator=gen, dtype=torch.float64)
    expected = torch.autograd.grad((general * weights).sum(), (factor, rhs))
    got = torch.autograd.grad((cholesky * weights).sum(), (factor, rhs))
    for g, e in zip(got, expected):
        torch.testing.assert_close(g, e, rtol=1e-10, atol=1e-12)
    assert torch.equal(solve_spd(_spd(factor), rhs), cholesky)  # the CPU's form


def test_a_matrix_that_is_not_positive_definite_gets_nan_in_its_env_only():
    gen = torch.Generator().manual_seed(3)
    matrix = _spd(torch.randn(N, 5, 5, generator=gen, dtype=torch.float64))
    matrix[1] = -matrix[1]  # negative definite: no Cholesky factor
    rhs = torch.randn(N, 5, generator=gen, dtype=torch.float64)
    solved = solve_spd(matrix, rhs)
    assert torch.isnan(solved[1]).all()
    keep = torch.tensor([0, 2])
    torch.testing.assert_close(solved[keep], torch.linalg.solve(matrix[keep], rhs[keep]), rtol=1e-12, atol=1e-12)
