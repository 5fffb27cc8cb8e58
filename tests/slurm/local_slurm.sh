#!/usr/bin/env bash
# A single-node Slurm (Debian's slurm-wlm 22.05 and munge) on this machine, for the Slurm test:
#   tests/slurm/local_slurm.sh install   # apt-get install slurm-wlm munge (root; idempotent)
#   tests/slurm/local_slurm.sh start     # munged, slurmctld, slurmd; waits until the node is idle
#   tests/slurm/local_slurm.sh stop      # stops what start started
# State and logs live in $SLURM_LOCAL (default /tmp/physicsrl-slurm). Exit status 3 means
# "cannot here" (not root, no apt, no slurm binaries): the caller skips, saying why.
set -euo pipefail
root=${SLURM_LOCAL:-/tmp/physicsrl-slurm}
conf=$root/slurm.conf
host=$(hostname -s)

cannot() { echo "local Slurm: cannot $1" >&2; exit 3; }

install() {
  command -v slurmctld >/dev/null && command -v munged >/dev/null && return 0
  [ "$(id -u)" = 0 ] || cannot "install slurm-wlm: not root"
  command -v apt-get >/dev/null || cannot "install slurm-wlm: no apt-get"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq >/dev/null && apt-get install -y -qq slurm-wlm munge >/dev/null \
    || cannot "install slurm-wlm: apt-get failed"
}

start() {
  command -v slurmctld >/dev/null || cannot "start: slurm-wlm is not installed"
  if [ -f "$conf" ] && [ "$(SLURM_CONF=$conf sinfo -h -o %t 2>/dev/null)" = idle ]; then
    echo "local Slurm already up: SLURM_CONF=$conf"; return 0
  fi
  [ "$(id -u)" = 0 ] || cannot "start slurmd: not root"
  mkdir -p "$root"/{state,spool,log,munge}
  cpus=$(nproc)
  memory=$(( $(awk '/MemTotal/ {print $2}' /proc/meminfo) / 1024 - 1024 ))
  cat > "$conf" <<CONF
ClusterName=physicsrl
SlurmctldHost=$host
SlurmUser=root
AuthType=auth/munge
CredType=cred/munge
MpiDefault=pmi2
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
ReturnToService=2
JobAcctGatherType=jobacct_gather/none
SlurmctldPidFile=$root/slurmctld.pid
SlurmdPidFile=$root/slurmd.pid
SlurmdSpoolDir=$root/spool
StateSaveLocation=$root/state
SlurmctldLogFile=$root/log/slurmctld.log
SlurmdLogFile=$root/log/slurmd.log
NodeName=$host CPUs=$cpus RealMemory=$memory State=UNKNOWN
PartitionName=local Nodes=$host Default=YES MaxTime=INFINITE State=UP OverSubscribe=FORCE:2
CONF
  export SLURM_CONF=$conf
  mkdir -p /run/munge
  pgrep -x munged >/dev/null || munged --force --pid-file="$root/munge/munged.pid" \
    --log-file="$root/log/munged.log" || cannot "start munged"
  slurmctld -f "$conf" || cannot "start slurmctld (see $root/log/slurmctld.log)"
  slurmd -f "$conf" || cannot "start slurmd (see $root/log/slurmd.log)"
  for _ in $(seq 60); do
    state=$(sinfo -h -o %t 2>/dev/null || true)
    [ "$state" = idle ] && { echo "local Slurm up: SLURM_CONF=$conf"; return 0; }
    sleep 1
  done
  stop >/dev/null
  cannot "bring node $host up (state: ${state:-none}; see $root/log)"
}

stop() {
  [ -f "$conf" ] || return 0
  export SLURM_CONF=$conf
  for _ in $(seq 20); do  # let finished jobs clear before their daemons go
    [ -z "$(squeue -h 2>/dev/null)" ] && break
    sleep 1
  done
  scancel --quiet --user="$(id -un)" 2>/dev/null || true
  for pid in "$root"/slurmd.pid "$root"/slurmctld.pid "$root"/munge/munged.pid; do
    [ -f "$pid" ] && kill "$(cat "$pid")" 2>/dev/null || true
  done
  echo "local Slurm stopped"
}

"$1"
