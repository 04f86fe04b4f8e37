#!/usr/bin/env bash
# This project's campaign: a declared study run in the background by `python -m torchrl_bail.study run`, beside work
# on this checkout, each finished job's results committed. The tool is the users' (docs/guides/studies.md); this only
# keeps it running and commits what it makes.
#
#   bash results/campaign.sh start STUDY DIR   # run STUDY from DIR/tree (this checkout's HEAD) on CPU $CAMPAIGN_CPUS (0)
#   bash results/campaign.sh status DIR        # runner, watcher, the last commit, then `study status`
#   bash results/campaign.sh stop DIR          # SIGTERM: the running job checkpoints; a later start resumes it
#
# DIR (outside the checkout, e.g. /work/campaign) holds a git worktree of this checkout's HEAD (tree/), the batches
# (data/), the run directories (work/outputs), the runner's log (queue.log) and the watcher's (watch.log). The jobs
# run from tree/, so editing or switching this checkout never changes the code of a job under way; `start` moves
# tree/ to HEAD first, which is why it refuses while a runner of DIR is alive. The watcher, whenever a run or a batch
# has finished and once more when the runner ends, gathers the kept runs and rebuilds the reports with this
# checkout's own code (`python -m torchrl_bail.study report`), then commits results/<the study's results> alone
# (never batches or checkpoints). A stopped or killed runner resumes on the next start: finished jobs are skipped,
# a stopped one continues from its checkpoint.
set -euo pipefail

usage() { sed -n '6,8p' "$0" | sed 's/^# *//' >&2; exit 2; }
alive() { [ -f "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }
root=$(cd "$(dirname "$0")/.." && pwd)   # the checkout: this script is its results/campaign.sh
study_cmd() { PYTHONPATH="$root/src" python -m torchrl_bail.study "$@"; }
# the finished runs and batches of DIR, one per line: what the watcher compares between passes
finished() {
  { find "$1/work/outputs" -name summary.json -printf '%P\n' 2>/dev/null
    find "$1/data" -mindepth 2 -maxdepth 2 -name metadata.json -printf '%P\n' 2>/dev/null; } | sort
}

command=${1:-}; shift || true
case "$command" in
start)
  [ $# -eq 2 ] || usage
  study=$1 dir=$2
  mkdir -p "$dir"; dir=$(cd "$dir" && pwd)
  if alive "$dir/runner.pid"; then
    echo "campaign.sh: a runner of $dir is alive (pid $(cat "$dir/runner.pid")); stop it first" >&2; exit 1
  fi
  study_cmd list "$study" > /dev/null   # an unknown or malformed study fails here, now
  if git -C "$dir/tree" rev-parse --is-inside-work-tree > /dev/null 2>&1; then
    git -C "$dir/tree" checkout -q -- . && git -C "$dir/tree" clean -fdq results
    git -C "$dir/tree" checkout -q --detach "$(git -C "$root" rev-parse HEAD)"
  else
    git -C "$root" worktree prune
    git -C "$root" worktree add -q --detach "$dir/tree" HEAD
  fi
  rm -f "$dir/runner.pid" "$dir/watcher.pid"
  echo "$study" > "$dir/study"
  run="echo \$\$ > ${dir@Q}/runner.pid; cd ${dir@Q}/tree && PYTHONPATH=${dir@Q}/tree/src exec python -m"
  run+=" torchrl_bail.study run ${study@Q} --workdir ${dir@Q}/work --data-dir ${dir@Q}/data"
  run+=" --cpus ${CAMPAIGN_CPUS:-0} >> ${dir@Q}/queue.log 2>&1"
  setsid nohup bash -c "$run" > /dev/null 2>&1 < /dev/null &
  setsid nohup bash "$root/results/campaign.sh" watch "$study" "$dir" >> "$dir/watch.log" 2>&1 < /dev/null &
  for _ in $(seq 50); do [ -s "$dir/runner.pid" ] && [ -s "$dir/watcher.pid" ] && break; sleep 0.1; done
  echo "campaign.sh: $study from tree/ at $(git -C "$dir/tree" rev-parse --short HEAD):" \
       "runner $(cat "$dir/runner.pid"), watcher $(cat "$dir/watcher.pid"); progress: bash $0 status $dir"
  ;;
watch)   # started by `start`: a commit of the study's results whenever runs or batches have finished
  study=$1 dir=$2
  echo $$ > "$dir/watcher.pid"
  cd "$root"
  results=$(PYTHONPATH="$root/src" python -c "import sys; from torchrl_bail.study import load_study
print(load_study(sys.argv[1]).results)" "$study")
  touch "$dir/committed.list"
  while true; do
    ended=$(alive "$dir/runner.pid" && echo 0 || echo 1)
    finished "$dir" > "$dir/finished.list"
    new=$(comm -13 "$dir/committed.list" "$dir/finished.list" | sed 's|/summary.json||; s|/metadata.json| (batch)|')
    if [ -n "$new" ] || [ "$ended" = 1 ]; then
      what=$(printf '%s\n' "$new" | grep . | paste -sd ';' | sed 's/;/; /g')
      # a failed report or commit (say, git busy with a commit of the checkout's own) is logged and retried at the
      # next pass, a minute later
      if study_cmd report "$study" --workdir "$dir/work" --data-dir "$dir/data" > /dev/null &&
         git add -- "$results"; then
        if git diff --cached --quiet -- "$results" ||
           git commit -q -m "Campaign ($study): ${what:-runner ended} — gathered and reported by study report" \
             -- "$results"; then
          cp "$dir/finished.list" "$dir/committed.list"
          echo "$(date -u '+%F %T') committed: ${what:-runner ended}"
        else echo "$(date -u '+%F %T') commit failed: ${what:-runner ended}"
        fi
      else echo "$(date -u '+%F %T') report failed: ${what:-runner ended}"
      fi
    fi
    if [ "$ended" = 1 ]; then exit 0; fi
    sleep 60
  done
  ;;
status)
  [ $# -eq 1 ] || usage
  dir=$(cd "$1" && pwd) study=$(cat "$1/study")
  for part in runner watcher; do
    if alive "$dir/$part.pid"; then echo "$part: alive (pid $(cat "$dir/$part.pid"))"
    else echo "$part: not running"; fi
  done
  grep -E ' (committed|commit failed|report failed): ' "$dir/watch.log" 2>/dev/null | tail -1 |
    sed 's/^/watcher, last: /' || true
  study_cmd status "$study" --workdir "$dir/work" --data-dir "$dir/data" | grep -v '  done$' || true
  ;;
stop)
  [ $# -eq 1 ] || usage
  dir=$(cd "$1" && pwd)
  if alive "$dir/watcher.pid"; then kill -- "-$(cat "$dir/watcher.pid")"; fi   # its session: a report under way too
  if alive "$dir/runner.pid"; then kill -TERM "$(cat "$dir/runner.pid")"; echo "campaign.sh: stopped $dir"; fi
  ;;
*) usage ;;
esac
