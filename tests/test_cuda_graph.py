"""--compile on a GPU: pebble.py's and rime.py's CudaGraph records whole steps (SAC's update with backward and
Adam, the target update, r_hat, the action) once and replays them. A replay runs no Python, so it is right only if
every tensor it reads and writes stays where the recording found it and the step's new tensors are copied into its
inputs. On the CPU, FakeCudaGraph stands in for torch's CUDA graph with those rules: the recording runs and keeps
each op with its tensors, a replay runs the kept ops again writing into the same tensors, and a sync (.item()) while
recording fails as it does on a GPU. With a GPU, the same checks run on real CUDA graphs."""

import contextlib
import functools

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
    sac_step = functools.partial(update or script.sac_update, actor=actor, critic=critic, critic_target=target,
                                 log_alpha=log_alpha, actor_opt=optimizers[0], critic_opt=optimizers[1],
                                 alpha_opt=optimizers[2], gamma=0.99)
    target_update = functools.partial(script.soft_update, critic, target, 0.005)
    if graphed:
        sac_step, target_update = script.CudaGraph(sac_step), script.CudaGraph(target_update)
    batches = torch.Generator().manual_seed(1)
    losses = []
    for call in range(1, calls + 1):
        batch = script.Batch(*(torch.randn(8, n, generator=batches).to(device) for n in (5, 2, 1, 5, 1)))
        rewards = batch.rewards * call  # not the batch's: the pre-training's kNN reward is passed apart
        losses.append({name: value.item() for name, value in sac_step(batch, rewards).items()})
        if call % 2 == 0:
            target_update()
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
    r_hat, act = pebble.CudaGraph(reward_model), pebble.CudaGraph(actor.sample)
    inputs = torch.Generator().manual_seed(1)
    for step in range(8):
        obs_action = torch.randn(7, generator=inputs).to(graphs)
        with torch.no_grad():
            replayed = r_hat(obs_action).clone()
            assert torch.allclose(replayed, reward_model(obs_action), rtol=1e-5, atol=1e-6)
            obs = obs_action[None, :5]
            torch.manual_seed(step)
            action = act(obs)[0].clone()
            torch.manual_seed(step)
            assert torch.allclose(action, actor.sample(obs)[0], rtol=1e-5, atol=1e-6)
        pebble.optimize(optimizer, reward_model(torch.randn(16, 7).to(graphs)).square().mean())
    assert r_hat.graph is not None and act.graph is not None
