"""A toy Dojo whose disk fills up during training: checkpoints at iterations 2 and 4, then a
file-size limit of half a checkpoint (``RLIMIT_FSIZE``: writes fail with EFBIG, as on a full
disk), training on to iteration 8. Prints the stop reason and the checkpoint directory's
listing as JSON. Usage: ``python dojo_full_disk.py <run directory>``."""

import json
import resource
import sys
from pathlib import Path

import torch
from train_toy_env import ToyChainEnv

from physicsrl import config as c
from physicsrl.builders import make_q_network
from physicsrl.coordinated import Coordinator
from physicsrl.dojo import Dojo

run = Path(sys.argv[1])
torch.manual_seed(0)
coordinator = Coordinator()
with coordinator:
    env = ToyChainEnv(coordinator, length=3)
    config = c.TrainConfig(
        buffer=c.BufferConfig(size=200, batch_size=16),
        collector=c.CollectorConfig(frames_per_batch=8),
        optim=c.OptimConfig(learning_starts=16, updates_per_batch=1),
        eval=c.Evaluation(every=0),
        logger=c.LoggerConfig(tensorboard=False, progress=False),
        checkpoint=c.CheckpointConfig(every=2),
    )
    dojo = Dojo(make_q_network(env, c.Network(hidden=[8])), env, config, log_dir=run)
    dojo.train(4, handle_signals=False)
    half = dojo.checkpoints.latest().stat().st_size // 2
    resource.setrlimit(resource.RLIMIT_FSIZE, (half, resource.RLIM_INFINITY))
    summary = dojo.train(8, handle_signals=False)
listing = sorted(p.name for p in (run / "checkpoints").iterdir())
print(
    json.dumps({"stopped": summary["stopped"], "iteration": summary["iteration"], "files": listing})
)
