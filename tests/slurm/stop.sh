#!/usr/bin/env bash
# Stops the test cluster that tests/slurm/start.sh started in STATE_DIR: cancels its jobs, then ends exactly the
# daemons named by its pid files (slurmd, slurmctld, slurmdbd, mariadbd, munged), each with SIGTERM and, after
# 20 s, SIGKILL. Nothing else on the machine is touched. Keeps the state directory (logs) unless --clean.
#   tests/slurm/stop.sh [STATE_DIR] [--clean]
set -uo pipefail
state=/tmp/torchrl_bail_slurm clean=0
for arg in "$@"; do
  case $arg in --clean) clean=1 ;; *) state=$arg ;; esac
done
[ $# -gt 0 ] || state=${TORCHRL_BAIL_SLURM_DIR:-$state}
state=$(realpath -m "$state")
export SLURM_CONF=$state/slurm.conf
[ -f "$SLURM_CONF" ] && timeout 10 scancel --full --quiet --user="$(id -un)" 2>/dev/null
for daemon in slurmd slurmctld slurmdbd mariadbd munged; do
  pid_file=$state/run/$daemon.pid
  [ -f "$pid_file" ] || continue
  pid=$(cat "$pid_file")
  if kill -0 "$pid" 2>/dev/null && [ "$(ps -o comm= -p "$pid")" = "$daemon" ]; then
    kill -TERM "$pid"
    for _ in $(seq 80); do kill -0 "$pid" 2>/dev/null || break; sleep 0.25; done
    kill -0 "$pid" 2>/dev/null && kill -KILL "$pid"
  fi
  rm -f "$pid_file"
done
[ "$clean" = 1 ] && rm -rf "$state"
exit 0
