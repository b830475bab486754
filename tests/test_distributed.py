"""Training with several processes (bench.distributed, DDP on gloo; no GPU needed): two processes follow
one process with the same global batch to float tolerance, only rank 0 writes, a stop asked on one rank
stops both at the same step, and the checkpoint resumes."""
import os
import signal
import socket
import sys
from multiprocessing import forkserver
from unittest import mock

import pandas as pd
import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from bench.models.srd import SRDNet
from bench.tasks import get_task
from bench.train import CHECKPOINT, TrainingInterrupted, train
from conftest import config_recipe
from test_train import WEIGHTS, SyntheticSequences

IMPORTED_IN = os.getpid()  # in a rank: the forkserver's, which imported this module for the ranks (_start_forkserver)
MODELS = {"srd": dict(channels=4, sr_blocks=1, dn_levels=2, dn_deform_blocks=1, cond_channels=4)}


class StopsOneRank(SyntheticSequences):
    """Sends SIGTERM to this process when it draws `draw` (as a scheduler would, to one rank)."""

    def __init__(self, term_at_draw=None):
        super().__init__()
        self.term_at_draw = term_at_draw

    def item(self, index, draw):
        if draw == self.term_at_draw:
            os.kill(os.getpid(), signal.SIGTERM)
        return super().item(index, draw)


def _recipe():
    return config_recipe(steps=6, batch_size=4, seq_len=2, crop=8, loss=WEIGHTS, checkpoint_every=100, warmup=0.2)


def _model():
    torch.manual_seed(0)
    return SRDNet(**MODELS["srd"])


def _term_in_backward(model, backward_index):
    """SIGTERM to this process during backward number `backward_index` (0-based): after the step's
    all-reduce of the loss, i.e. after the ranks agreed whether to stop at this step."""
    calls = []

    def hook(grad):
        calls.append(1)
        if len(calls) == backward_index + 1:
            os.kill(os.getpid(), signal.SIGTERM)
    next(model.parameters()).register_hook(hook)


def _rank(rank, port, out_dir, term_at_draw, term_rank, term_backward, results):
    assert IMPORTED_IN != os.getpid() and "torch._dynamo" in sys.modules, \
        "the forkserver did not preload this module and TorchDynamo: each rank imports them again"
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    torch.set_num_threads(1)
    dist.init_process_group("gloo", rank=rank, world_size=2)
    try:
        data = StopsOneRank(term_at_draw if rank == term_rank else None)
        model = _model()
        if term_backward is not None and rank == term_rank:
            _term_in_backward(model, term_backward)
        try:
            summary = train(model, data, get_task("srd"), out_dir, _recipe(), progress=False,
                            distributed_ranks=True)
            outcome = {"steps": summary["steps"]}
        except TrainingInterrupted as err:
            outcome = {"interrupted": str(err)}
        results[rank] = {**outcome, "state": {k: v.clone() for k, v in model.state_dict().items()}}
    finally:
        dist.destroy_process_group()


def _start_forkserver():
    """Each rank a fresh process, forked from a server that imported this module, torch and TorchDynamo (the
    first optimizer imports it) once per test run, not each of the file's 10 ranks (6-7 s of CPU a rank).
    The forkserver imports what it preloads without this process's sys.path (Python 3.11's ignores the
    sys_path it is given) and skips, silently, a module it cannot import: PYTHONPATH gives it the path
    (`_rank` checks the preload took). This process's PYTHONPATH is put back; the server, and the ranks it
    forks, keep the one they started with. A server already running is kept (what it preloaded stays)."""
    mp.set_forkserver_preload([__name__, "torch._dynamo"])
    with mock.patch.dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p)):
        forkserver.ensure_running()


def _two_ranks(out_dir, term_at_draw=None, term_rank=1, term_backward=None):
    with socket.socket() as s:  # a free port for the rendezvous
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    _start_forkserver()  # first: where forkserver is the default start method, the Manager would start it
    results = mp.Manager().dict()
    mp.start_processes(_rank, args=(port, str(out_dir), term_at_draw, term_rank, term_backward, results), nprocs=2,
                       start_method="forkserver")
    return dict(results)


@pytest.fixture(scope="module")
def one_process(tmp_path_factory):
    out = tmp_path_factory.mktemp("one")
    model = _model()
    torch.set_num_threads(1)
    train(model, SyntheticSequences(), get_task("srd"), out, _recipe(), progress=False)
    return model.state_dict(), pd.read_csv(out / "curve.csv")


def _assert_close(state, expected):
    for key, value in expected.items():
        torch.testing.assert_close(state[key], value, rtol=1e-4, atol=1e-6, msg=key)


def test_two_processes_follow_one_with_the_same_global_batch(one_process, tmp_path):
    expected_state, expected_curve = one_process
    results = _two_ranks(tmp_path)
    assert results[0]["steps"] == results[1]["steps"] == 6
    _assert_close(results[0]["state"], expected_state)
    _assert_close(results[1]["state"], expected_state)  # every rank ends with the same (EMA) weights
    curve = pd.read_csv(tmp_path / "curve.csv")  # written by rank 0: the global batch's loss
    pd.testing.assert_series_equal(curve["loss"], expected_curve["loss"], rtol=1e-5)
    pd.testing.assert_series_equal(curve["grad_norm"], expected_curve["grad_norm"], rtol=1e-4)


def test_a_stop_on_one_rank_stops_both_and_the_checkpoint_resumes(one_process, tmp_path):
    expected_state, _ = one_process
    # rank 1 draws slots 1 and 3 of each batch of 4: draw 2 * 4 + 1 is in step 2 (0-based)
    stopped = _two_ranks(tmp_path, term_at_draw=2 * 4 + 1, term_rank=1)
    assert all("SIGTERM at step 3 of 6" in stopped[r]["interrupted"] for r in (0, 1)), stopped
    assert torch.load(tmp_path / CHECKPOINT, weights_only=False)["step"] == 3
    resumed = _two_ranks(tmp_path)
    assert resumed[0]["steps"] == 6
    _assert_close(resumed[0]["state"], expected_state)
    assert len(pd.read_csv(tmp_path / "curve.csv")) == 6


def test_a_stop_after_the_ranks_agreed_on_this_step_stops_both_at_the_next(one_process, tmp_path):
    """A signal during rank 1's backward of step 3 (after the all-reduce): both finish step 3, agree to
    stop at step 4, rank 0 writes the checkpoint, and the run resumes to the one-process weights."""
    expected_state, _ = one_process
    stopped = _two_ranks(tmp_path, term_rank=1, term_backward=2)
    assert all("SIGTERM at step 4 of 6" in stopped[r]["interrupted"] for r in (0, 1)), stopped
    assert torch.load(tmp_path / CHECKPOINT, weights_only=False)["step"] == 4
    _assert_close(_two_ranks(tmp_path)[0]["state"], expected_state)


def test_a_batch_that_does_not_split_over_the_ranks_is_refused(monkeypatch, tmp_path):
    from bench import distributed
    from bench.errors import UserError
    monkeypatch.setattr(distributed, "rank_and_size", lambda: (0, 3))
    with pytest.raises(UserError, match="batch_size=4 is not divisible by the 3 processes"):
        train(_model(), SyntheticSequences(), get_task("srd"), tmp_path, _recipe(), progress=False,
              distributed_ranks=True)


def test_only_the_pipeline_trains_with_the_other_ranks(monkeypatch, tmp_path):
    """train() called directly (adopt's replays, the stability probes) trains alone under torchrun."""
    from bench import distributed
    monkeypatch.setattr(distributed, "rank_and_size", lambda: (0, 3))
    summary = train(_model(), SyntheticSequences(), get_task("srd"), tmp_path, _recipe(), progress=False)
    assert summary["steps"] == 6
