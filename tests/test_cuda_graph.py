"""--compile on a GPU: pebble.py's and rime.py's CudaGraph records whole steps (SAC's update with backward and
Adam, the target update, r_hat, the action) once and replays them. A replay runs no Python, so it is right only if
every tensor it reads and writes stays where the recording found it and the step's new tensors are copied into its
inputs; a call with other shapes, dtypes or arguments is refused, and torch.compile may not compile while it records.
On the CPU, FakeCudaGraph stands in for torch's CUDA graph with those rules: the recording runs and keeps each op
with its tensors, a replay runs the kept ops again writing into the same tensors, and a sync (.item()) while
recording fails as it does on a GPU. With a GPU, the same checks run on real CUDA graphs."""

import contextlib

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

import pebble
import rime

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no GPU"))]


def tensors(value):
    if torch.is_tensor(value):
        return [value]
    return [t for v in value for t in tensors(v)] if isinstance(value, (list, tuple)) else []


class FakeCudaGraph(TorchDispatchMode):
    """Records the ops run while capturing; replay() runs them again into the recorded outputs."""

    def __init__(self):
        super().__init__()
        self.ops = []
        self.just_captured = False

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if func is torch.ops.aten._local_scalar_dense.default:
            raise RuntimeError("a sync while capturing a CUDA graph")
        out = func(*args, **(kwargs or {}))
        self.ops.append((func, args, kwargs or {}, out))
        return out

    def replay(self):
        if self.just_captured:  # the capture ran the ops once already (a GPU would record, then replay)
            self.just_captured = False
            return
        with torch.no_grad():  # kernels only, as a GPU replays them
            for func, args, kwargs, out in self.ops:
                for fixed, new in zip(tensors(out), tensors(func(*args, **kwargs))):
                    if fixed.data_ptr() != new.data_ptr():  # a new tensor: into the recorded one
                        fixed.copy_(new)


@contextlib.contextmanager
def fake_capture(graph):
    with graph:
        yield
    graph.just_captured = True


class NoStream:
    def wait_stream(self, stream):
        pass


@pytest.fixture
def graphs(request, monkeypatch):
    """The device; on the CPU, torch.cuda's graph and stream calls replaced by the fakes."""
    if request.param == "cpu":
        monkeypatch.setattr(torch.cuda, "CUDAGraph", FakeCudaGraph)
        monkeypatch.setattr(torch.cuda, "graph", fake_capture)
        monkeypatch.setattr(torch.cuda, "Stream", NoStream)
        monkeypatch.setattr(torch.cuda, "current_stream", NoStream)
        monkeypatch.setattr(torch.cuda, "stream", lambda stream: contextlib.nullcontext())
    return torch.device(request.param)


def sac_run(script, device, graphed, calls=12, reset_at=6, update=None):
    """`calls` SAC updates and target updates (every 2nd), pebble's critic reset after `reset_at`: (losses, state)."""
    torch.manual_seed(0)
    actor = script.Actor(5, 2, 16, 2).to(device)
    critic, target = (script.TwinCritic(5, 2, 16, 2).to(device) for _ in range(2))
    log_alpha = torch.zeros((), device=device, requires_grad=True)
    capturable = graphed and device.type == "cuda"
    optimizers = [script.adam(p, 1e-3, capturable) for p in (actor.parameters(), critic.parameters(), [log_alpha])]
    sac_update, soft_update = update or script.sac_update, script.soft_update
    if graphed:  # as the script's main block: the same calls, through CudaGraph
        sac_update, soft_update = script.CudaGraph(sac_update), script.CudaGraph(soft_update)
    batches = torch.Generator().manual_seed(1)
    losses = []
    for call in range(1, calls + 1):
        batch = script.Batch(*(torch.randn(8, n, generator=batches).to(device) for n in (5, 2, 1, 5, 1)))
        rewards = batch.rewards * call  # not the batch's: the pre-training's kNN reward is passed apart
        losses.append({name: value.item() for name, value in sac_update(batch, rewards, actor, critic, target,
                                                                        log_alpha, *optimizers, 0.99).items()})
        if call % 2 == 0:
            soft_update(critic, target, 0.005)
        if call == reset_at and script is pebble:
            pebble.reset_critic(critic, target, optimizers[1])
    state = [*actor.parameters(), *critic.parameters(), *target.parameters(), log_alpha]
    state += [value for optimizer in optimizers for s in optimizer.state.values() for value in s.values()]
    return losses, [t.detach().cpu() for t in state]


@pytest.mark.parametrize("graphs", DEVICES, indirect=True)
@pytest.mark.parametrize("script", [pebble, rime], ids=["pebble", "rime"])
def test_replayed_sac_updates_are_the_eager_ones(script, graphs):
    """3 eager calls, the recording, then replays: every update's losses, the weights and Adam's moments as eager,
    bit for bit on the CPU. pebble's critic reset comes after the recording: it must reset the tensors the graph
    holds (in place), not make new ones."""
    eager_losses, eager_state = sac_run(script, graphs, graphed=False)
    losses, state = sac_run(script, graphs, graphed=True)
    assert len(state) == len(eager_state) and len(losses) == 12
    if graphs.type == "cpu":
        assert losses == eager_losses
        assert all(torch.equal(a, b) for a, b in zip(state, eager_state))
    else:  # the same kernels; float tolerance all the same
        for eager, replayed in zip(eager_losses, losses):
            assert replayed == pytest.approx(eager, rel=1e-4, abs=1e-5)
        assert all(torch.allclose(a, b, rtol=1e-4, atol=1e-5) for a, b in zip(state, eager_state))
    torch.manual_seed(0)
    assert not torch.equal(state[0], script.Actor(5, 2, 16, 2).net[0].weight.detach())  # the updates moved it


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no GPU")
def test_replayed_compiled_sac_updates_are_the_compiled_ones():
    """--compile on a GPU: torch.compile's kernels (its own random draws) inside the recorded graph, against the
    same compiled function called eagerly."""
    import torch._dynamo

    torch._dynamo.reset()
    compiled = torch.compile(pebble.sac_update)
    eager_losses, eager_state = sac_run(pebble, torch.device("cuda"), graphed=False, update=compiled)
    losses, state = sac_run(pebble, torch.device("cuda"), graphed=True, update=compiled)
    for eager, replayed in zip(eager_losses, losses):
        assert replayed == pytest.approx(eager, rel=1e-4, abs=1e-5)
    assert all(torch.allclose(a, b, rtol=1e-4, atol=1e-5) for a, b in zip(state, eager_state))


def test_reset_critic_zeroes_adams_moments_in_place():
    """The critic reset gives what fresh moments give (pebble's reference: a new optimizer) in the tensors Adam has:
    the graph keeps writing to those."""
    torch.manual_seed(0)
    critic = pebble.TwinCritic(3, 1, 8, 1)
    optimizer = pebble.adam(critic.parameters(), 1e-3)
    pebble.optimize(optimizer, sum(q.sum() for q in critic(torch.randn(4, 3), torch.randn(4, 1))))
    held = [value for s in optimizer.state.values() for value in s.values()]
    assert len(held) == 3 * len(list(critic.parameters())) and any(t.abs().sum() > 0 for t in held)
    pebble.reset_critic(critic, pebble.TwinCritic(3, 1, 8, 1), optimizer)
    assert [value for s in optimizer.state.values() for value in s.values()] == held  # the same tensors
    assert all(not t.any() for t in held)  # step 0, zero moments: Adam's start
    fresh = pebble.TwinCritic(3, 1, 8, 1)
    fresh.load_state_dict(critic.state_dict())
    fresh_optimizer = pebble.adam(fresh.parameters(), 1e-3)  # the reference's way: new moments
    obs, action = torch.randn(4, 3), torch.randn(4, 1)
    for net, opt in ((critic, optimizer), (fresh, fresh_optimizer)):
        for _ in range(3):
            pebble.optimize(opt, sum(q.square().sum() for q in net(obs, action)))
    assert all(torch.equal(a, b) for a, b in zip(critic.parameters(), fresh.parameters()))


@pytest.mark.parametrize("graphs", DEVICES, indirect=True)
def test_replayed_reward_model_and_actor_follow_their_weights(graphs):
    """r_hat and the action are recorded once; the reward model keeps learning (Adam steps outside the graph) and
    each replay reads its new weights and the new input, with fresh noise for the action each step."""
    torch.manual_seed(0)
    reward_model = pebble.RewardEnsemble(5, 2, 3).to(graphs)
    optimizer = pebble.adam(reward_model.parameters(), 1e-2)
    actor = pebble.Actor(5, 2, 16, 2).to(graphs)
    learned_reward, act = pebble.CudaGraph(pebble.learned_reward), pebble.CudaGraph(pebble.act)
    inputs = torch.Generator().manual_seed(1)
    for step in range(8):
        obs_action = torch.randn(7, generator=inputs).to(graphs)
        with torch.no_grad():
            replayed = learned_reward(reward_model, obs_action).clone()
            assert torch.allclose(replayed, reward_model(obs_action).mean(), rtol=1e-5, atol=1e-6)
            obs = obs_action[:5]
            torch.manual_seed(step)
            action = act(actor, obs).clone()
            torch.manual_seed(step)
            assert torch.allclose(action, actor.sample(obs[None])[0][0], rtol=1e-5, atol=1e-6)
        pebble.optimize(optimizer, reward_model(torch.randn(16, 7).to(graphs)).square().mean())
    assert learned_reward.graph is not None and act.graph is not None


@pytest.mark.parametrize("graphs", DEVICES, indirect=True)
def test_a_call_with_other_shapes_dtypes_or_arguments_is_refused(graphs):
    """copy_ would broadcast a smaller batch into the recorded one and zip would drop what does not fit: a replay
    would then train on the wrong data. CudaGraph refuses such a call, before it copies anything."""
    torch.manual_seed(0)
    actor = pebble.Actor(5, 2, 16, 2).to(graphs)
    critic, target = (pebble.TwinCritic(5, 2, 16, 2).to(graphs) for _ in range(2))
    log_alpha = torch.zeros((), device=graphs, requires_grad=True)
    capturable = graphs.type == "cuda"
    optimizers = [pebble.adam(p, 1e-3, capturable) for p in (actor.parameters(), critic.parameters(), [log_alpha])]
    sac_update = pebble.CudaGraph(pebble.sac_update)

    def batch(rows=8, dtype=torch.float32):
        return pebble.Batch(*(torch.randn(rows, n, device=graphs, dtype=dtype) for n in (5, 2, 1, 5, 1)))

    for _ in range(5):  # 3 eager calls, the recording, a replay
        good = batch()
        sac_update(good, good.rewards, actor, critic, target, log_alpha, *optimizers, 0.99)
    held = [t.clone() for t in pebble.flat_inputs(sac_update.inputs) if torch.is_tensor(t)]
    weights = [p.detach().clone() for p in actor.parameters()]
    smaller, wider = batch(rows=4), batch()
    doubles = batch(dtype=torch.float64)
    calls = [(smaller, smaller.rewards, 0.99),  # broadcast into 8 rows
             (wider, torch.randn(8, 2, device=graphs), 0.99),  # rewards of another shape
             (doubles, doubles.rewards, 0.99),  # another dtype
             (good, good.rewards, 0.9)]  # another discount: the recorded one would be used
    for new_batch, rewards, gamma in calls:
        with pytest.raises(ValueError, match="sac_update: its CUDA graph was recorded for other tensor shapes"):
            sac_update(new_batch, rewards, actor, critic, target, log_alpha, *optimizers, gamma)
    with pytest.raises(ValueError):  # another optimizer than the recorded one
        sac_update(good, good.rewards, actor, critic, target, log_alpha, *optimizers[:2],
                   pebble.adam([log_alpha], 1e-3, capturable), 0.99)
    assert all(torch.equal(a, b) for a, b in zip(held, (t for t in pebble.flat_inputs(sac_update.inputs)
                                                        if torch.is_tensor(t))))
    assert all(torch.equal(a, b) for a, b in zip(weights, actor.parameters()))  # nothing replayed
    sac_update(good, good.rewards, actor, critic, target, log_alpha, *optimizers, 0.99)  # the same call replays
    assert not all(torch.equal(a, b) for a, b in zip(weights, actor.parameters()))


class NoGraph:
    """A CUDA graph that records and replays nothing: the capture only runs the function."""

    def replay(self):
        pass


@pytest.mark.parametrize("grad_mode_while_recording, recompiles", [(False, False), (True, True)])
def test_torch_compile_may_not_compile_while_a_graph_records(monkeypatch, grad_mode_while_recording, recompiles):
    """A compiled function whose guards fail at the recording (here: grad mode, no_grad in the eager calls) would be
    compiled inside the capture; CudaGraph makes that an error. With the guards held, the recording goes through."""
    import torch._dynamo

    monkeypatch.setattr(torch.cuda, "CUDAGraph", NoGraph)
    monkeypatch.setattr(torch.cuda, "graph", lambda graph: contextlib.nullcontext())
    monkeypatch.setattr(torch.cuda, "Stream", NoStream)
    monkeypatch.setattr(torch.cuda, "current_stream", NoStream)
    monkeypatch.setattr(torch.cuda, "stream", lambda stream: contextlib.nullcontext())
    torch._dynamo.reset()

    def scaled(x):
        return x * 2 if torch.is_grad_enabled() else x * 3

    graph = pebble.CudaGraph(torch.compile(scaled, backend="eager"))
    with torch.no_grad():
        for _ in range(3):
            assert torch.equal(graph(torch.ones(3)), torch.full((3,), 3.0))
    with torch.set_grad_enabled(grad_mode_while_recording):
        if recompiles:
            with pytest.raises(RuntimeError, match="Detected recompile"):
                graph(torch.ones(3))
        else:
            assert torch.equal(graph(torch.ones(3)), torch.full((3,), 3.0))
    assert torch.equal(torch.compile(scaled, backend="eager")(torch.ones(3)), torch.full((3,), 2.0))  # elsewhere
