"""A PNG strip of one episode: the field u after the reset and after every decision, the
electrode positions (catheter observation), the shocks (ATP) marked, and the integral of u at
each decision beside the success threshold. Leader only, inside ``with coordinator:``; one
extra parallel call per decision gathers the field.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from tensordict import TensorDict


def render_episode(env, policy, seed: int, path: str | Path, columns: int = 8) -> dict:
    """Play one episode of ``env`` (seeded with ``seed``) with ``policy``, draw it to ``path``;
    return the actions, rewards and integrals of u (after the reset and each decision)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle
    from matplotlib.tri import Triangulation

    task = env.task
    env.set_seed(seed)
    td = env.reset()
    frames, actions, rewards, elapsed = [task.field()], [], [], [0]
    while True:
        td = policy(td)
        out = env.step(td)["next"]
        actions.append(int(td["action"]))
        rewards.append(out["reward"].item())
        frames.append(task.field())
        elapsed.append(getattr(task, "intervals", len(actions)))  # ATP: with extra waits
        if out["done"].item():
            break
        td = TensorDict({k: v for k, v in out.items() if k != "reward"}, batch_size=[])

    triangulation = Triangulation(*frames[0][0].T)
    low, high = min(f[1].min() for f in frames), max(f[1].max() for f in frames)
    rows = -(-len(frames) // columns)
    figure = plt.figure(figsize=(2.2 * columns, 2.3 * rows + 2.4))
    grid = figure.add_gridspec(rows + 1, columns, height_ratios=[1] * rows + [1.0])
    electrodes = getattr(task.observation, "positions", lambda: None)()
    shock = getattr(task.config, "shock", None)
    for i, (_, values, _) in enumerate(frames):
        ax = figure.add_subplot(grid[i // columns, i % columns])
        ax.tripcolor(triangulation, values, shading="gouraud", vmin=low, vmax=high, cmap="inferno")
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        if electrodes is not None:
            ax.plot(*electrodes.T, "o", color="cyan", markersize=1.5)
        shocked = i > 0 and actions[i - 1] == 1 and shock is not None
        if shocked:
            ax.add_patch(Circle(shock.centre, shock.radius, fill=False, color="red", ls="--", lw=1))
        label = "after reset" if i == 0 else f"after decision {i}" + (" (shock)" if shocked else "")
        if elapsed[i] > i:
            label += f" + {elapsed[i] - i} waits"
        ax.set_title(label, fontsize=8, color="red" if shocked else "black")
    timeline = figure.add_subplot(grid[rows, :])
    interval = getattr(task.config, "decision_interval", 1.0)
    times = np.array(elapsed) * interval
    integrals = [f[2] for f in frames]
    timeline.plot(times, integrals, "o-", label="integral of u")
    threshold = getattr(task.config, "success_threshold", None)
    if threshold is not None:
        timeline.axhline(threshold, color="green", lw=1, label="success threshold")
    for k, action in enumerate(actions):
        if action == 1:
            timeline.axvspan(
                times[k],
                times[k] + shock.duration,
                color="red",
                alpha=0.25,
                label="shock" if k == actions.index(1) else None,
            )
    timeline.set_xlabel("time after the reset")
    timeline.set_ylabel("integral of u")
    timeline.legend(fontsize=8, loc="upper right")
    figure.suptitle(
        f"{task.name} episode, seed {seed}: actions {actions}, return "
        f"{sum(rewards):g}; electrodes in cyan, shock disk dashed red",
        fontsize=10,
    )
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)
    return {"actions": actions, "rewards": rewards, "integrals": integrals}
