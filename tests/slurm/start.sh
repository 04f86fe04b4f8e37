#!/usr/bin/env bash
# Starts a single-node Slurm cluster on localhost for the test suite: munged, a MariaDB server, slurmdbd (so that
# sacct works), slurmctld and slurmd, each with its pid file under the state directory, so that stop.sh ends exactly
# the daemons this script started. Needs Debian's slurmctld, slurmd, slurmdbd, slurm-client, munge and
# mariadb-server (.ci/run installs them), and root.
#
#   tests/slurm/start.sh [STATE_DIR]     # default: $TORCHRL_BAIL_SLURM_DIR or /tmp/torchrl_bail_slurm
#   export SLURM_CONF=STATE_DIR/slurm.conf   # then sbatch, squeue, sacct, scontrol talk to this cluster
#   tests/slurm/stop.sh [STATE_DIR]
#
# Prints the SLURM_CONF path on success; exits non-zero (with the failing daemon's log) otherwise.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
state=$(realpath -m "${1:-${TORCHRL_BAIL_SLURM_DIR:-/tmp/torchrl_bail_slurm}}")
ctld_port=${TORCHRL_BAIL_SLURM_PORT:-16817}
slurmd_port=$((ctld_port + 1)) dbd_port=$((ctld_port + 2)) db_port=$((ctld_port + 3))
cred_expire=${TORCHRL_BAIL_SLURM_CRED_EXPIRE:-10}
export SLURM_CONF=$state/slurm.conf

fail() { echo "start.sh: $1" >&2; [ -n "${2:-}" ] && [ -f "$2" ] && tail -n 30 "$2" >&2; exit 1; }
alive() { [ -f "$state/run/$1.pid" ] && kill -0 "$(cat "$state/run/$1.pid")" 2>/dev/null; }
wait_for() {  # wait_for WHAT LOG SECONDS COMMAND...: until COMMAND succeeds (each try at most 5 s)
  local what=$1 log=$2 seconds=$3; shift 3
  local deadline=$((SECONDS + seconds))
  while [ $SECONDS -lt $deadline ]; do timeout 5 "$@" >/dev/null 2>&1 && return 0; sleep 0.25; done
  fail "$what did not come up in $seconds s" "$log"
}
for tool in munged mungekey mariadbd mariadb-install-db slurmdbd slurmctld slurmd sacctmgr sinfo; do
  command -v "$tool" >/dev/null || fail "$tool not found (apt-get install slurmctld slurmd slurmdbd slurm-client munge mariadb-server)"
done
mkdir -p "$state"/{run,log,ctld,spool,munge,mysql}
chmod 700 "$state/munge"

host=$(hostname -s)
cpus=$(nproc)
mem_mb=$(( $(awk '/MemTotal/ {print $2}' /proc/meminfo) / 1024 - 512 ))
for conf in slurm slurmdbd; do
  sed -e "s|@STATE@|$state|g" -e "s|@HOST@|$host|g" -e "s|@CPUS@|$cpus|g" -e "s|@MEM_MB@|$mem_mb|g" \
      -e "s|@CTLD_PORT@|$ctld_port|g" -e "s|@SLURMD_PORT@|$slurmd_port|g" -e "s|@DBD_PORT@|$dbd_port|g" \
      -e "s|@DB_PORT@|$db_port|g" -e "s|@CRED_EXPIRE@|$cred_expire|g" "$here/$conf.conf.in" > "$state/$conf.conf"
done
chmod 600 "$state/slurmdbd.conf"

# munge on its standard socket (Slurm's clients talk to no other): a munged already serving it (the machine's own)
# is used as it is; otherwise one is started with a key of this cluster's own (root needs --force)
socket=/run/munge/munge.socket.2
if ! timeout 5 bash -c "munge -n | unmunge" >/dev/null 2>&1; then
  [ -f "$state/munge/munge.key" ] || mungekey --create --keyfile="$state/munge/munge.key" --force
  chmod 600 "$state/munge/munge.key"
  mkdir -p "$(dirname "$socket")"
  munged --force --socket="$socket" --key-file="$state/munge/munge.key" --pid-file="$state/run/munged.pid" \
    --log-file="$state/log/munged.log" --seed-file="$state/munge/munge.seed"
fi
wait_for munged "$state/log/munged.log" 10 bash -c "munge -n | unmunge"

# MariaDB: a server of the cluster's own, on 127.0.0.1 and a socket in the state directory
sql=(mariadb --no-defaults --socket="$state/run/mysqld.sock" -u root)
if [ ! -d "$state/mysql/mysql" ]; then
  mariadb-install-db --no-defaults --user=root --datadir="$state/mysql" --auth-root-authentication-method=socket \
    --skip-test-db > "$state/log/mariadb-install.log" 2>&1 || fail "mariadb-install-db failed" "$state/log/mariadb-install.log"
fi
if ! alive mariadbd; then
  mariadbd --no-defaults --user=root --datadir="$state/mysql" --socket="$state/run/mysqld.sock" \
    --bind-address=127.0.0.1 --port="$db_port" --pid-file="$state/run/mariadbd.pid" \
    --log-error="$state/log/mariadb.log" --innodb-buffer-pool-size=64M --skip-log-bin > /dev/null 2>&1 &
fi
wait_for mariadbd "$state/log/mariadb.log" 60 "${sql[@]}" -e "SELECT 1"
"${sql[@]}" -e "CREATE USER IF NOT EXISTS 'slurm'@'127.0.0.1' IDENTIFIED BY 'slurm';
        CREATE USER IF NOT EXISTS 'slurm'@'localhost' IDENTIFIED BY 'slurm';
        GRANT ALL ON slurm_acct_db.* TO 'slurm'@'127.0.0.1'; GRANT ALL ON slurm_acct_db.* TO 'slurm'@'localhost';"

alive slurmdbd || slurmdbd
wait_for slurmdbd "$state/log/slurmdbd.log" 60 sacctmgr -n list cluster
sacctmgr -i add cluster tbail > /dev/null 2>&1 || true   # slurmctld registers with the cluster's record
alive slurmctld || slurmctld
wait_for slurmctld "$state/log/slurmctld.log" 60 scontrol ping
alive slurmd || slurmd
wait_for slurmd "$state/log/slurmd.log" 60 bash -c "sinfo -h -o %T -p debug | grep -qx idle"
echo "$SLURM_CONF"
