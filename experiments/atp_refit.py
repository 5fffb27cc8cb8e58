"""Refit a run's Q-network on its replay buffers: does a better fit of the same experience make
a better greedy policy?

    python experiments/atp_refit.py CHECKPOINT OUT.torchrl [--buffers CHECKPOINT ...]
        [--hidden 256,256] [--ensemble K] [--updates 40000] [--batch 512] [--lr 3e-4]
        [overrides ...]

The Q-network of CHECKPOINT (its weights as the start; with ``--hidden``, a new network of those
widths, its input normaliser fitted to the transitions) is trained with the run's DQN loss (the
run's discount and target network; the transitions hold its n-step returns and training
rewards, as the Dojo stored them) on the transitions in the replay buffers of CHECKPOINT and of
each ``--buffers`` checkpoint: ``--updates`` Adam steps on ``--batch`` transitions drawn
uniformly, the learning rate decayed from ``--lr`` to 0 by a cosine. ``--ensemble K`` (with
``--hidden``): K networks fitted so from seeds ``--seed`` + 0..K-1, written as one network whose
Q-values are their mean (:func:`mean_network`: widths K x hidden). OUT is a policy file
(as store_policy.py writes) that ``physicsrl-eval run=OUT`` evaluates. The overrides change the
run's config for the env that sizes the network, which never steps (e.g. ``env.replicas=1
env.model.compile=false``).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
from store_policy import KEPT, write_policy  # noqa: E402

from physicsrl import builders  # noqa: E402
from physicsrl.checkpoint import read  # noqa: E402
from physicsrl.cli.eval import run_config  # noqa: E402
from physicsrl.config import BufferConfig, typed  # noqa: E402
from physicsrl.coordinated import Coordinator  # noqa: E402


def transitions(checkpoint: str, size: int):
    """The transitions in the replay buffer of ``checkpoint`` (a buffer of ``size``)."""
    buffer = builders.make_buffer(BufferConfig(size=size))
    buffer.load_state_dict(read(checkpoint, ["replay_buffer"])["replay_buffer"])
    return buffer[: len(buffer)]


def mean_network(members: list, wide) -> None:
    """Load into ``wide`` (a Q-network of K x the members' widths) the weights that make its
    Q-values the mean of the K ``members``' (the same inputs and normaliser): the first layer's
    rows stacked, the hidden layers' blocks on the diagonal, the output layer's columns side by
    side divided by K."""
    k = len(members)
    states = [member.state_dict() for member in members]
    merged = dict(states[0])  # the normaliser's state, and the structure
    weights = [key for key in merged if key.endswith(".weight")]
    for key in weights:
        layer = [state[key] for state in states]
        biases = [state[key.replace(".weight", ".bias")] for state in states]
        if key == weights[0]:
            merged[key], bias = torch.cat(layer), torch.cat(biases)
        elif key == weights[-1]:
            merged[key], bias = torch.cat(layer, 1) / k, torch.stack(biases).mean(0)
        else:
            merged[key], bias = torch.block_diag(*layer), torch.cat(biases)
        merged[key.replace(".weight", ".bias")] = bias
    wide.load_state_dict(merged)


def fit(q_network, data, env, config, args) -> tuple[float, float]:
    """Train ``q_network`` on the transitions ``data``; return the DQN loss on them before and
    after."""
    loss = builders.make_loss(q_network, env, config.loss)
    target_updater = builders.make_target_updater(loss, config.loss.target)
    optimizer = builders.make_optimizer(loss, args.lr, 0.0)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, max(args.updates, 1))
    with torch.no_grad():
        before = float(loss(data)["loss"])
    for _ in range(args.updates):
        batch = data[torch.randint(len(data), (args.batch,))]
        value = loss(batch)["loss"]
        optimizer.zero_grad()
        value.backward()
        if config.optim.grad_clip:
            torch.nn.utils.clip_grad_norm_(loss.parameters(), config.optim.grad_clip)
        optimizer.step()
        schedule.step()
        target_updater.step()
    with torch.no_grad():
        return before, float(loss(data)["loss"])


def main() -> None:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument("checkpoint", help="a training checkpoint (with its replay buffer)")
    parser.add_argument("out", type=Path, help="the policy file to write")
    parser.add_argument("--buffers", nargs="*", default=[], help="more checkpoints' transitions")
    parser.add_argument("--hidden", help="a new network of these widths, e.g. 256,256")
    parser.add_argument("--ensemble", type=int, default=1, help="K networks, their mean")
    parser.add_argument("--updates", type=int, default=40_000)
    parser.add_argument("--batch", type=int, default=512)
    parser.add_argument("--lr", type=float, default=3e-4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("overrides", nargs="*", help="Hydra overrides of the run's config")
    args = parser.parse_intermixed_args()
    if args.out.exists():
        parser.error(f"{args.out} exists: name a new file")
    if args.ensemble < 1 or (args.ensemble > 1 and not args.hidden):
        parser.error(f"--ensemble {args.ensemble}: K >= 1, and K > 1 needs --hidden")
    states = read(args.checkpoint, KEPT)
    network = states["extra"]["config"]["agent"]["network"]
    hidden = [int(width) for width in args.hidden.split(",")] if args.hidden else None
    if hidden:
        network["hidden"] = hidden
    cfg = run_config(states["extra"]["config"], args.overrides)
    config = typed(cfg)
    torch.set_num_threads(config.threads)  # as training (threads=1: one core)
    coordinator = Coordinator()
    with coordinator:
        env = builders.make_env(cfg, coordinator)
        sources = [args.checkpoint, *args.buffers]
        data = torch.cat([transitions(source, config.buffer.size) for source in sources])
        members = []
        for seed in range(args.seed, args.seed + args.ensemble):
            torch.manual_seed(seed)
            q_network = builders.make_q_network(env, config.agent.network)
            if hidden:
                inputs = builders.Inputs.concat(*(data[key] for key in q_network.in_keys))
                builders.normalizer_of(q_network).fit(inputs)
            else:
                q_network.load_state_dict(states["q_network"])
            before, after = fit(q_network, data, env, config, args)
            members.append(q_network)
        if args.ensemble > 1:
            network["hidden"] = [args.ensemble * width for width in hidden]
            wide = replace(config.agent.network, hidden=network["hidden"])
            q_network = builders.make_q_network(env, wide)
            mean_network(members, q_network)
    write_policy(args.out, {**states, "q_network": q_network.state_dict()})
    print(
        f"{args.out}: {args.ensemble} x {args.updates} updates on {len(data)} transitions of "
        f"{len(sources)} checkpoint(s); DQN loss on them {before:.4g} before, {after:.4g} after"
        + (" (the last member)" if args.ensemble > 1 else "")
    )


if __name__ == "__main__":
    main()
