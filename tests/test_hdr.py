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
