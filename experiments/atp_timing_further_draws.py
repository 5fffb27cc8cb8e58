"""The timing variant's agent against the open-loop schedules on further draws, paired per draw.

    python experiments/atp_timing_further_draws.py
    python experiments/atp_timing_further_draws.py --out OUT --folder FOLDER
        --agent "NAME=CSV" ... --first-shock "NAME=POLICY" ...

The table's 20 held-out draws measure a success rate to about +-11 points; this compares the
stored run-4 policy (and run 2's) with the schedules on the draws labelled by
``atp_shock_timing.py`` (seeds 2000000000, ...), which neither training nor any choice about
the policies used. It reads, under ``--out``:

- ``atp_timing_labelled_draws/atp_timing_agent_eval.csv`` (and ``..._run2_...``): the
  policies on those draws (``physicsrl-eval``, the commands in ``atp_timing_agent.txt`` there);
- ``<experiment>_open_loop_per_seed.csv`` in ``atp_timing_labelled_draws/`` and its folders:
  every open-loop schedule on the draws of each search (``atp_baselines.py --open-loop
  --first-seed 2000000000``, and ``2000000048`` in ``draws_48_95/``);
- ``<experiment>_two_shocks_per_seed.csv`` there or below: schedules of two shocks on the draws
  that none of the above ends (``atp_baselines.py --open-loop --two-shocks 1,2,3``);
- ``atp_shock_timing_labels/``: whether a single shock at each decision ends each draw,
  and the supervised reference's leave-one-draw-out choice (``atp_shock_timing.txt``).

``--folder`` and ``--agent NAME=CSV`` (repeated) name other evaluations, e.g. of another
variant whose labels are under ``--out``. ``--first-shock NAME=POLICY`` (repeated) scores a
stored policy's first shock from the labels alone: before its first shock a policy sees the
never-shock episode's observations, so its greedy Q-values there give the decision of that
shock (:func:`first_shocks`), and the labels whether that shock alone ends the draw.

Prints a Markdown table, for the draws of each search and for all the labelled draws: mean
return, success and shocks, and for each other policy the draws that only the first agent ends
and those that only the other policy ends. The hindsight oracles pick the best row per draw
after seeing them all (not policies): no policy in the table ends more draws. The last one adds the
two-shock schedules, tried only on the draws that nothing else ends: its success is that of
the best choice of everything tried, its return is not printed (it would be a lower bound).
"""

from __future__ import annotations

import argparse
import sys
from functools import partial
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))
from atp_baselines import hindsight  # noqa: E402
from atp_shock_timing import (  # noqa: E402
    Neighbours,
    choose,
    leave_one_draw_out,
    load_labels,
    outcomes,
)

from physicsrl import builders  # noqa: E402
from physicsrl.checkpoint import read  # noqa: E402
from physicsrl.cli.eval import run_config  # noqa: E402
from physicsrl.config import typed  # noqa: E402
from physicsrl.tables import mean_metrics, read_per_policy  # noqa: E402

FOLDER = "atp_timing_labelled_draws"
SEARCH = "*_open_loop_per_seed.csv"  # each search of the schedules, in FOLDER or below
PAIRS = "*_two_shocks_per_seed.csv"  # two-shock schedules, in FOLDER or below
AGENTS = {  # stored policies' evaluations on the labelled draws; the first is paired with all
    "run 4, iteration 100": "atp_timing_agent_eval.csv",
    "run 2, iteration 90": "atp_timing_run2_agent_eval.csv",
}


def labels(out: Path) -> tuple[list[int], np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(seeds, x, single (draws, decisions), never (draws,), reference (draws,)): the labels
    (:func:`load_labels`) and the success of the supervised reference (its neighbours and theta
    as ``fit`` chooses them from all the labels) on each draw with that draw left out."""
    seeds, x, single, never = load_labels(out)
    k, theta, _ = choose(x, single, never)
    p = leave_one_draw_out(x, single, partial(Neighbours, k=k))
    reference = outcomes(p, single, never, theta)
    return seeds, x, single, never, reference


def first_shocks(policy: Path, x: np.ndarray) -> np.ndarray:
    """(draws,): the decision of the first shock of the stored greedy policy ``policy`` on each
    labelled draw (-1: none), from the never-shock episodes' features ``x`` (draws, decisions,
    readings + decision index; NaN where not seen), which its network must read as its inputs
    ``[observation, step]``."""
    states = read(policy, ["q_network", "extra"])
    network = typed(run_config(states["extra"]["config"], [])).agent.network
    if network.inputs != ["observation", "step"]:
        raise ValueError(f"{policy}: reads {network.inputs}, not the labels' [observation, step]")
    module = builders.q_values(x.shape[-1], 2, network)
    prefix = "module.0.module."  # the QValueActor's module
    module.load_state_dict({k.removeprefix(prefix): v for k, v in states["q_network"].items()})
    with torch.no_grad():
        q = module(torch.from_numpy(np.nan_to_num(x)).float())
    shock = (q[..., 1] > q[..., 0]).numpy() & ~np.isnan(x[..., 0])
    return np.array([np.flatnonzero(row)[0] if row.any() else -1 for row in shock])


def agreement(schedules: dict[int, dict[str, dict]], seeds: list[int], single: np.ndarray):
    """(agreeing, compared): the (draw, decision) pairs where a search's "single shock at k"
    and the label say the same of the shock's success, of those both cover: two implementations
    of the same episodes."""
    agreeing = compared = 0
    for d, seed in enumerate(seeds):
        for k in range(single.shape[1]):
            searched = schedules.get(seed, {}).get(f"single shock at {k}")
            if searched is not None:
                compared += 1
                agreeing += float(searched["success"]) == single[d, k]
    return agreeing, compared


def named(pairs: list[str] | None, default: dict[str, str]) -> dict[str, str]:
    """``["NAME=VALUE", ...]`` as a dict (None: ``default``)."""
    if pairs is None:
        return default
    return dict(pair.rsplit("=", 1) for pair in pairs)


def row(name: str, draws: str, means: dict, success=None, agent=None) -> str:
    """A table row; with ``success`` and ``agent`` (per draw), the draws ended by one only."""
    cells = [f"{means[k]:.2f}" if k in means else "" for k in ("return", "success", "shocks")]
    cells[1] = f"{100 * means['success']:.1f}%"
    paired = "" if success is None else f"{(agent > success).sum()} / {(success > agent).sum()}"
    return f"| {name} | {draws} | {' | '.join(cells)} | {paired} |"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("experiments/results"))
    parser.add_argument("--folder", default=FOLDER, help="the evaluations' folder under --out")
    parser.add_argument("--agent", action="append", help="NAME=CSV in --folder (repeated)")
    parser.add_argument("--first-shock", action="append", help="NAME=POLICY file (repeated)")
    args = parser.parse_args()
    out, folder, agents = args.out, args.out / args.folder, named(args.agent, AGENTS)
    seeds, x, single, never, reference = labels(out)
    by_seed = {
        name: {int(r["seed"]): r for r in read_per_policy(folder / csv)["greedy DQN"]}
        for name, csv in agents.items()
    }
    firsts = {name: first_shocks(Path(p), x) for name, p in named(args.first_shock, {}).items()}
    schedules: dict[int, dict[str, dict]] = {}  # seed -> schedule -> its row
    blocks = []  # the draws of each search, then all the labelled draws
    for csv in sorted(folder.glob(f"**/{SEARCH}")):
        rows = read_per_policy(csv)
        for policy, per_seed in rows.items():
            for r in per_seed:
                schedules.setdefault(int(r["seed"]), {})[policy] = r
        blocks.append([int(r["seed"]) for r in next(iter(rows.values()))])
    pairs = {}  # two-shock schedule -> its rows
    for csv in folder.glob(f"**/{PAIRS}"):
        pairs |= read_per_policy(csv)
    first = next(iter(agents))
    print(f"| policy | draws | return | success | shocks | draws only {first} ends / only this |")
    print("| --- | --- | --- | --- | --- | --- |")
    for draws in blocks + ([seeds] if seeds not in blocks else []):
        span = f"{draws[0] % 1000:02d}-{draws[-1] % 1000:02d}"  # the draws by their last digits
        index = [seeds.index(s) for s in draws]
        runs = {name: [by_seed[name][s] for s in draws] for name in agents}
        agent = np.array([r["success"] for r in next(iter(runs.values()))], float)
        for i, (name, rows) in enumerate(runs.items()):
            won = np.array([r["success"] for r in rows], float)
            paired = (won, agent) if i else (None, None)  # the first is paired with the rest
            print(row(name, span, mean_metrics(rows), *paired))
        if all(s in schedules for s in draws):
            per_policy = {p: [schedules[s][p] for s in draws] for p in schedules[draws[0]]}
            means = {p: mean_metrics(r) for p, r in per_policy.items()}
            best = max(means, key=lambda p: (means[p]["return"], means[p]["success"]))
            won = np.array([r["success"] for r in per_policy[best]], float)
            name = f"best open-loop schedule: {best}"
            print(row(name, span, means[best], won, agent))
            print(row("hindsight oracle of the schedules", span, hindsight(per_policy)))
            name = "hindsight oracle of the schedules and the runs"
            print(row(name, span, hindsight(per_policy | runs)))
            if pairs and draws == seeds:
                tried = {r["seed"] for rows in pairs.values() for r in rows}
                name = f"... and {len(pairs)} two-shock schedules, tried on {len(tried)} draws"
                oracle = hindsight(per_policy | runs | pairs)
                print(row(name, span, {"success": oracle["success"]}))
        best_single = int(single[index].mean(0).argmax())
        won = single[index, best_single]
        name = f"single shock at {best_single} (labels)"
        print(row(name, span, {"success": won.mean()}, won, agent))
        won = np.maximum(single[index].max(1), never[index])
        print(
            row(
                "single shocks, the best per draw with hindsight (labels)",
                span,
                {"success": won.mean()},
            )
        )
        won = reference[index]
        name = "supervised reference, leave-one-draw-out (labels)"
        print(row(name, span, {"success": won.mean()}, won, agent))
        for name, shots in firsts.items():
            won = np.array([single[d, k] if k >= 0 else never[d] for d, k in enumerate(shots)])
            won = won[index]
            print(row(f"{name}: its first shock alone (labels)", span, {"success": won.mean()}))
    agreeing, compared = agreement(schedules, seeds, single)
    if compared:
        agree = f"agree on {agreeing} of {compared} draws x decisions"
        print(f"\nthe labels and the searches' single shocks {agree}")


if __name__ == "__main__":
    main()
