"""The paper's coefficient network: layer shapes, parameter count, residual path, determinism."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch  # noqa: E402 - the [nn] extra, part of [test]

from kautztwin.exceptions import DataError  # noqa: E402
from kautztwin.nn import PaperNetwork, paper_parameter_count  # noqa: E402

torch.set_num_threads(1)

BRANCHES = [[256, 128, 64, 32], [128, 64, 32], [64, 32], [32]]


def _count(net: torch.nn.Module) -> int:
    return sum(p.numel() for p in net.parameters() if p.requires_grad)


def test_layer_shapes_match_the_paper():
    net = PaperNetwork(900)
    assert len(net.branches) == 4
    for branch, widths in zip(net.branches, BRANCHES, strict=True):
        layers = list(branch)
        assert len(layers) == 2 * len(widths)
        linears, prelus = layers[0::2], layers[1::2]
        assert all(isinstance(m, torch.nn.Linear) for m in linears)
        assert all(isinstance(m, torch.nn.PReLU) for m in prelus)
        assert [m.in_features for m in linears] == [900, *widths[:-1]]
        assert [m.out_features for m in linears] == widths
    assert (net.head.in_features, net.head.out_features) == (32, 1)


def test_parameter_count_of_the_paper_network_by_formula():
    # branch inputs 480 (n + 1), deeper layers 257*128 + 2*129*64 + 3*65*32 = 55648,
    # ten shared PReLU slopes and the head 33 * n_out
    n = 900
    expected = 480 * (n + 1) + (257 * 128 + 2 * 129 * 64 + 3 * 65 * 32) + 10 + 33 * 1
    assert expected == 488_171
    assert _count(PaperNetwork(n)) == expected
    assert paper_parameter_count(n) == expected


@pytest.mark.parametrize(
    ("n_inputs", "n_outputs"), [(900, 4), (10, 1), (1, 3)], ids=["900x4", "10x1", "1x3"]
)
def test_parameter_count_formula_for_other_sizes(n_inputs, n_outputs):
    net = PaperNetwork(n_inputs, n_outputs)
    assert _count(net) == 480 * n_inputs + 56_138 + 33 * n_outputs
    assert paper_parameter_count(n_inputs, n_outputs) == _count(net)


@pytest.mark.parametrize("n_outputs", [1, 4], ids=["single", "multi"])
def test_forward_of_a_batch(n_outputs):
    torch.manual_seed(0)
    net = PaperNetwork(900, n_outputs)
    out = net(torch.randn(8, 900))
    assert out.shape == (8, n_outputs)
    assert out.dtype == torch.float32
    assert bool(torch.isfinite(out).all())


def test_forward_in_float64():
    torch.manual_seed(0)
    net = PaperNetwork(20, 2).double()
    assert net(torch.randn(3, 20, dtype=torch.float64)).dtype == torch.float64


def test_output_is_head_of_softmax_plus_summed_features():
    torch.manual_seed(1)
    net = PaperNetwork(50, 3)
    captured: list[torch.Tensor] = []
    hooks = [b.register_forward_hook(lambda m, i, o: captured.append(o)) for b in net.branches]
    x = torch.randn(6, 50, dtype=torch.float32)
    with torch.no_grad():
        out = net(x)
    for h in hooks:
        h.remove()
    assert len(captured) == 4 and all(c.shape == (6, 32) for c in captured)
    s = captured[0] + captured[1] + captured[2] + captured[3]
    torch.testing.assert_close(net.features(x), s, rtol=1e-6, atol=1e-6)
    expected = net.head(torch.softmax(s, dim=1) + s)
    torch.testing.assert_close(out, expected, rtol=1e-6, atol=1e-6)
    # the residual path matters: the softmax alone gives another output
    without_residual = net.head(torch.softmax(s, dim=1))
    assert not torch.allclose(out, without_residual, atol=1e-3)


def test_same_seed_gives_identical_networks_and_outputs():
    x = torch.randn(4, 30, generator=torch.Generator().manual_seed(5))
    nets = []
    for _ in range(2):
        torch.manual_seed(123)
        nets.append(PaperNetwork(30, 2))
    for p, q in zip(nets[0].parameters(), nets[1].parameters(), strict=True):
        assert torch.equal(p, q)
    assert torch.equal(nets[0](x), nets[1](x))
    torch.manual_seed(124)
    other = PaperNetwork(30, 2)
    assert not torch.equal(other.head.weight, nets[0].head.weight)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [({"n_inputs": 0}, "n_inputs"), ({"n_inputs": 9.5}, "n_inputs"),
     ({"n_inputs": 9, "n_outputs": 0}, "n_outputs"), ({"n_inputs": True}, "n_inputs")],
    ids=["zero-inputs", "float-inputs", "zero-outputs", "bool-inputs"],
)
def test_invalid_sizes_raise(kwargs, match):
    with pytest.raises(DataError, match=match):
        PaperNetwork(**kwargs)


def test_import_kautztwin_does_not_import_torch():
    code = "import sys, kautztwin; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_kautztwin_nn_without_torch_names_the_extra():
    code = (
        "import sys\n"
        "class Block:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name == 'torch' or name.startswith('torch.'):\n"
        "            raise ImportError(f'No module named {name!r}')\n"
        "sys.meta_path.insert(0, Block())\n"
        "import kautztwin\n"
        "try:\n    import kautztwin.nn\nexcept ImportError as e:\n    print(e)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert "pip install 'kautztwin[nn]'" in out.stdout
