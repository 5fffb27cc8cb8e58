"""Refit a run's Q-network on its replay buffers: does a better fit of the same experience make
a better greedy policy?

    python experiments/atp_refit.py CHECKPOINT OUT.torchrl [--buffers CHECKPOINT ...]
        [--hidden 256,256] [--updates 40000] [--batch 512] [--lr 3e-4] [overrides ...]

The Q-network of CHECKPOINT (its weights as the start; with ``--hidden``, a new network of those
widths, its input normaliser fitted to the transitions) is trained with the run's DQN loss (the
run's discount and target network; the transitions hold its n-step returns and training
rewards, as the Dojo stored them) on the transitions in the replay buffers of CHECKPOINT and of
each ``--buffers`` checkpoint: ``--updates`` Adam steps on ``--batch`` transitions drawn
uniformly, the learning rate decayed from ``--lr`` to 0 by a cosine. OUT is a policy file
(as store_policy.py writes) that ``physicsrl-eval run=OUT`` evaluates. The overrides change the
run's config for the env that sizes the network, which never steps (e.g. ``env.replicas=1
env.model.compile=false``).
"""

from __future__ import annotations

import argparse
import sys
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


def main() -> None:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument("checkpoint", help="a training checkpoint (with its replay buffer)")
    parser.add_argument("out", type=Path, help="the policy file to write")
    parser.add_argument("--buffers", nargs="*", default=[], help="more checkpoints' transitions")
    parser.add_argument("--hidden", help="a new network of these widths, e.g. 256,256")
    parser.add_argument("--updates", type=int, default=40_000)
    parser.add_argument("--batch", type=int, default=512)
    parser.add_argument("--lr", type=float, default=3e-4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("overrides", nargs="*", help="Hydra overrides of the run's config")
    args = parser.parse_intermixed_args()
    states = read(args.checkpoint, KEPT)
    network = states["extra"]["config"]["agent"]["network"]
    if args.hidden:
        network["hidden"] = [int(width) for width in args.hidden.split(",")]
    cfg = run_config(states["extra"]["config"], args.overrides)
    config = typed(cfg)
    torch.set_num_threads(config.threads)  # as training (threads=1: one core)
    torch.manual_seed(args.seed)
    coordinator = Coordinator()
    with coordinator:
        env = builders.make_env(cfg, coordinator)
        q_network = builders.make_q_network(env, config.agent.network)
        sources = [args.checkpoint, *args.buffers]
        data = torch.cat([transitions(source, config.buffer.size) for source in sources])
        if args.hidden:
            inputs = builders.Inputs.concat(*(data[key] for key in q_network.in_keys))
            builders.normalizer_of(q_network).fit(inputs)
        else:
            q_network.load_state_dict(states["q_network"])
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
            after = float(loss(data)["loss"])
    write_policy(args.out, {**states, "q_network": q_network.state_dict()})
    print(
        f"{args.out}: {args.updates} updates on {len(data)} transitions of {len(sources)} "
        f"checkpoint(s); DQN loss on them {before:.4g} before, {after:.4g} after"
    )


if __name__ == "__main__":
    main()
