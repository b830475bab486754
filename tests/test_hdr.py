import pytest
import torch

from bench.hdr import from_network, to_network


@pytest.mark.parametrize("mode,lo,hi", [("clamp", 0.0, 1.0), ("log1p", 0.0, 1e4), ("pu", 1e-4, 100.0)])
def test_round_trip_on_valid_range(mode, lo, hi):
    x = torch.logspace(torch.log10(torch.tensor(max(lo, 1e-4))), torch.log10(torch.tensor(hi)), 200,
                       dtype=torch.float64)
    back = from_network(to_network(x, mode), mode)
    assert torch.allclose(back, x, rtol=1e-6, atol=1e-9)


def test_pu_maps_one_to_one_and_is_monotonic():
    x = torch.logspace(-4, 2, 500, dtype=torch.float64)
    y = to_network(x, "pu")
    assert to_network(torch.tensor(1.0, dtype=torch.float64), "pu").item() == pytest.approx(1.0)
    assert (y[1:] > y[:-1]).all()


def test_unknown_mode_is_rejected():
    with pytest.raises(ValueError, match="unknown HDR transform"):
        to_network(torch.zeros(1), "gamma")


@pytest.mark.parametrize("mode", ["clamp", "pu"])
def test_bounded_domains_invert_any_network_output_to_a_finite_radiance(mode):
    """A network can output anything; far above PU21's range its inverse formula has a pole.
    (log1p is unbounded by design: its inverse overflows only past radiance 3e38.)"""
    y = torch.tensor([-1e6, -5.0, 0.0, 0.5, 3.0, 10.0, 1e3, 1e9, float("inf")])
    assert torch.isfinite(from_network(y, mode)).all()
    top = from_network(torch.tensor([1e9, float("inf")]), mode)
    assert top.tolist() == pytest.approx([100.0, 100.0] if mode == "pu" else [1.0, 1.0])
