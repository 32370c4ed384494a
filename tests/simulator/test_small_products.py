"""The small batched products of the step (`spatial.small_matmul`, `small_matvec`): the broadcast
form a GPU runs gives ``@``'s values and gradients at every shape the simulator multiplies, here
on the CPU in float64 (the CPU itself keeps ``@``, bit for bit)."""
import pytest
import torch

from torchrl_diffenvs.articulated.spatial import small_matmul, small_matvec

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
