"""The simulator's speed paths give the same numbers as the plain ones (issue 25 item 4).

Fused Hessian assembly (sim._fused, terms.FusedBlocks): the membrane and Gauss–Newton hinge
blocks are computed and added into the CSR data in one pass. The result must be the same bits
as computing the [M, 3k, 3k] blocks (the numba kernels held to numpy in test_sim_kernels.py)
and scattering them, on a compressed, crumpled sheet where the membrane projection acts.
"""

import cloth_grid
import numpy as np
import pytest

from physavatar.sim.assembly import Assembler
from physavatar.sim.energies import Bending, Membrane
from physavatar.sim.mesh import ClothTopology
from physavatar.sim.terms import Blocks, Diagonal, FusedBlocks


@pytest.fixture
def sheet():
    V, F = cloth_grid.grid(7, 1.0)
    topo = ClothTopology.build(V, F)
    rng = np.random.default_rng(3)
    x = V * np.array([0.7, 0.8, 1.0]) + 0.05 * rng.normal(size=V.shape)
    return topo, x


@pytest.mark.parametrize("model", ["stvk", "neohookean"])
def test_fused_assembly_is_bit_identical_to_block_scatter(sheet, model):
    topo, x = sheet
    n = len(x)
    m = Membrane(topo, 37.0, 0.3, model)
    b = Bending(topo, 1e-3)
    b.projection = "gauss_newton"
    dof_map = np.arange(3 * n)
    dof_map[:6] = -1  # two prescribed vertices: their entries go to the dump slot
    dof_map[6:] -= 6
    asm = Assembler(dof_map, [topo.faces, topo.hinges], topo.hinges[:, 2:])
    fused = [m.hessian(x, True), b.hessian(x, True), Diagonal(np.full(3 * n, 2.0))]
    assert all(isinstance(h, FusedBlocks) for h in fused[:2])
    plain = [Blocks(h.index, np.array(h.values)) for h in fused[:2]] + fused[2:]
    H_fused, H_plain = asm.assemble(fused), asm.assemble(plain)
    assert np.array_equal(H_fused.indptr, H_plain.indptr) and np.array_equal(H_fused.indices, H_plain.indices)
    assert np.array_equal(H_fused.data, H_plain.data)  # the same bits, not merely close
    # the blocks it adds are the kernels' (the membrane clamp acted: not the unprojected blocks)
    assert not np.allclose(m.hessian(x, True).values, m.hessian(x, False).values)
    # and an independent reference: the numpy twins' blocks, scattered by scipy
    ref = asm.assemble_numpy([m.hessian_numpy(x, True), b.hessian_numpy(x, "gauss_newton"), fused[2]])
    assert np.abs((H_fused - ref).data).max() <= 1e-9 * np.abs(ref.data).max()


def test_fused_blocks_read_their_values_at_the_state_they_were_made(sheet):
    """The values are computed when read: a later change of the positions array must not leak in."""
    topo, x = sheet
    m = Membrane(topo, 37.0, 0.3, "stvk")
    y = x.copy()
    h = m.hessian(y, True)
    expected = m.hessian(x, True).values
    y += 0.1
    assert np.array_equal(h.values, expected)
