#!/usr/bin/env bash
# A study's long queue in the background, beside work on this checkout, with each finished job's results committed.
#
#   bash results/campaign.sh start STUDY DIR [REGEX ...]   # the queue: each REGEX's jobs in turn (none: the study's)
#   bash results/campaign.sh status DIR                    # runner, watcher, last commit; each job's state, time left
#   bash results/campaign.sh stop DIR                      # SIGTERM: the running jobs checkpoint, a later start resumes
#
# DIR (outside the checkout, e.g. /work/campaign) holds a git worktree of this checkout's HEAD (tree/), the batches
# (data/), the run directories and job logs (work/), the queue's log (queue.log) and the watcher's (watch.log).
# The jobs run from tree/, so editing or switching this checkout never changes the code of a job under way; `start`
# moves tree/ to HEAD first, which is why it refuses while a runner of DIR is alive. The runner is
# `results/run_study.py --jobs N --pin` (N: $CAMPAIGN_JOBS, default every core), each job alone on a core of its
# own; it records each job's cost straight into this checkout's results/STUDY/timings.json. The watcher, on every
# job that ends and once more when the runner ends, gathers the kept runs and rebuilds the reports with this
# checkout's own code (`run_study.py --report-only`), then commits results/STUDY alone (never batches or
# checkpoints). A stopped or killed queue resumes on the next start: finished runs are kept (and the costs of jobs
# that ended after the watcher's last pass are merged first), a killed job continues from its checkpoint, and a
# batch whose data dir was lost is made again and checked against its kept metadata.
set -euo pipefail

usage() { sed -n '4,6p' "$0" | sed 's/^# *//' >&2; exit 2; }
alive() { [ -f "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }

# The costs the runner recorded in tree/results/STUDY/timings.json that this checkout's record lacks, merged into it
# (written whole or not at all): by the watcher after each job, and by `start` before it moves tree/ to HEAD.
keep_costs() {
  PYTHONPATH="$root/src" python - "$2/tree/results/$1/timings.json" "$root/results/$1/timings.json" <<'PY'
import json, sys
from pathlib import Path
from torchrl_bail.core.io import write_text_atomic
ran, kept = map(Path, sys.argv[1:])
old = json.loads(kept.read_text()) if kept.is_file() else {}
new = {k: v for k, v in (json.loads(ran.read_text()) if ran.is_file() else {}).items() if k not in old}
if new:  # in run_study.py's record_job_end format
    write_text_atomic(kept, json.dumps({**old, **new}, indent=1, sort_keys=True) + "\n")
PY
}

root=$(cd "$(dirname "$0")/.." && pwd)   # the checkout: this script is its results/campaign.sh
command=${1:-}; shift || true

case "$command" in
start)
  [ $# -ge 2 ] || usage
  study=$1 dir=$2; shift 2
  mkdir -p "$dir"; dir=$(cd "$dir" && pwd)
  if alive "$dir/runner.pid"; then
    echo "campaign.sh: a runner of $dir is alive (pid $(cat "$dir/runner.pid")); stop it first" >&2; exit 1
  fi
  python "$root/results/run_study.py" --study "$study" --list > /dev/null   # an unknown study fails here, now
  if git -C "$dir/tree" rev-parse --is-inside-work-tree > /dev/null 2>&1; then
    if [ -f "$dir/study" ]; then keep_costs "$(cat "$dir/study")" "$dir"; fi   # the last jobs' costs, not lost
    git -C "$dir/tree" checkout -q -- . && git -C "$dir/tree" clean -fdq results
    git -C "$dir/tree" checkout -q --detach "$(git -C "$root" rev-parse HEAD)"
  else
    git -C "$root" worktree prune
    git -C "$root" worktree add -q --detach "$dir/tree" HEAD
  fi
  run=(python results/run_study.py --study "$study" --workdir "$dir/work" --data-dir "$dir/data"
       --jobs "${CAMPAIGN_JOBS:-$(nproc)}" --pin)
  log=$dir/queue.log
  # each process writes its own pid: the runner's is its session's, so that `stop` reaches every job under it
  phases="echo \$\$ > ${dir@Q}/runner.pid; cd ${dir@Q}/tree && export PYTHONPATH=${dir@Q}/tree/src || exit 1; "
  for regex in "${@:-.}"; do phases+="${run[*]@Q} --only ${regex@Q} >> ${log@Q} 2>&1 || exit 1; "; done
  rm -f "$dir/runner.pid" "$dir/watcher.pid"
  echo "$study" > "$dir/study"
  setsid nohup bash -c "$phases" > /dev/null 2>&1 < /dev/null &
  setsid nohup bash "$root/results/campaign.sh" watch "$study" "$dir" >> "$dir/watch.log" 2>&1 < /dev/null &
  for _ in $(seq 50); do [ -s "$dir/runner.pid" ] && [ -s "$dir/watcher.pid" ] && break; sleep 0.1; done
  echo "campaign.sh: $study from tree/ at $(git -C "$dir/tree" rev-parse --short HEAD):" \
       "runner $(cat "$dir/runner.pid"), watcher $(cat "$dir/watcher.pid"); progress:" \
       "python results/run_study.py --study $study --workdir $dir/work --data-dir $dir/data --status"
  ;;
watch)   # started by `start`: one commit of results/STUDY per job that ends, while the runner lives
  study=$1 dir=$2
  echo $$ > "$dir/watcher.pid"
  cd "$root"
  seen=0
  while true; do
    done_before=$(alive "$dir/runner.pid" && echo 0 || echo 1)
    lines=$(grep -E '^\[[0-9]+/[0-9]+\]' "$dir/queue.log" 2>/dev/null || true)
    count=$(printf '%s' "$lines" | grep -c . || true)
    if [ "$count" -ne "$seen" ] || [ "$done_before" = 1 ]; then   # and once more as the runner ends
      seen=$count
      last=$(printf '%s' "$lines" | tail -1)
      # a failed report or commit (say, git busy with a commit of the checkout's own) is logged and retried at the
      # next pass, a minute later
      if keep_costs "$study" "$dir" &&
         PYTHONPATH="$root/src" python results/run_study.py --study "$study" --workdir "$dir/work" \
           --data-dir "$dir/data" --report-only && git add -- "results/$study"; then
        if git diff --cached --quiet -- "results/$study"; then :
        elif git commit -q -m "Campaign ($study): ${last:-runner ended} — gathered and reported by --report-only" \
               -- "results/$study"; then echo "$(date -u '+%F %T') committed: ${last:-runner ended}"
        else seen=$((seen - 1)); echo "$(date -u '+%F %T') commit failed: ${last:-runner ended}"
        fi
      else seen=$((seen - 1)); echo "$(date -u '+%F %T') report failed: ${last:-runner ended}"
      fi
    fi
    if [ "$done_before" = 1 ] && [ "$seen" -ge "$count" ]; then exit 0; fi
    sleep 60
  done
  ;;
status)
  [ $# -ge 1 ] || usage
  dir=$(cd "$1" && pwd) study=$(cat "$1/study")
  for part in runner watcher; do
    if alive "$dir/$part.pid"; then echo "$part: alive (pid $(cat "$dir/$part.pid"))"
    else echo "$part: not running"; fi
  done
  grep -E '^\[[0-9]+/[0-9]+\]' "$dir/queue.log" 2>/dev/null | tail -3 || true
  grep -E ' (committed|commit failed|report failed): ' "$dir/watch.log" 2>/dev/null | tail -1 |
    sed 's/^/watcher, last: /' || true
  python "$root/results/run_study.py" --study "$study" --workdir "$dir/work" --data-dir "$dir/data" \
    --jobs "${CAMPAIGN_JOBS:-$(nproc)}" --status | grep -v '^done ' || true
  ;;
stop)
  [ $# -ge 1 ] || usage
  dir=$(cd "$1" && pwd)
  if alive "$dir/watcher.pid"; then kill -- "-$(cat "$dir/watcher.pid")"; fi   # its session: a report under way too
  if alive "$dir/runner.pid"; then kill -TERM -- "-$(cat "$dir/runner.pid")"; echo "campaign.sh: stopped $dir"; fi
  ;;
*) usage ;;
esac
