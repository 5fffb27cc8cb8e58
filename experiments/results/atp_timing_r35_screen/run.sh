#!/bin/bash
cd /work/main && source .venv/bin/activate
S="never shock"; for d in $(seq 0 11); do S="$S,single shock at $d"; done
for r in 35 30 40; do
  mpiexec -n 2 python experiments/atp_baselines.py --experiment atp_timing --open-loop --first-seed 3000000000 --seeds 10 --schedules "$S" --out /tmp/screen/r$r \
    env.shock.radius=$r env.model.backend=torch env.replicas=65 env.model.compile=true env.model.dtype=float32 > /tmp/screen/r$r.log 2>&1
done
