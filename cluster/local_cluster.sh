#!/usr/bin/env bash
# A one-machine "cluster" from Debian's packages, for the tests, CI and trying the cluster set-up before using a real
# one: SLURM (munged + slurmctld + slurmd, no accounting database) and an MLflow tracking server with a PostgreSQL
# backend store and a local artifact root. Everything lives under $AVATARLAB_CLUSTER_DIR (default /tmp/avatarlab-cluster).
#
#   cluster/local_cluster.sh install   # apt-get the Debian packages (root) and pip the Python drivers into .venv
#   cluster/local_cluster.sh up        # start SLURM + PostgreSQL + MLflow; prints the environment to use
#   cluster/local_cluster.sh env       # the exports: SLURM_CONF, MLFLOW_TRACKING_URI
#   cluster/local_cluster.sh down      # stop everything (state stays in the folder)
#   cluster/local_cluster.sh status
set -euo pipefail

DIR="${AVATARLAB_CLUSTER_DIR:-/tmp/avatarlab-cluster}"
REPO="$(cd "$(dirname "$0")/.." && pwd)"
PYTHON="${PYTHON:-$REPO/.venv/bin/python}"
PG_BIN="$(ls -d /usr/lib/postgresql/*/bin 2>/dev/null | sort -V | tail -1)"
PG_PORT="${AVATARLAB_PG_PORT:-55432}"
MLFLOW_PORT="${AVATARLAB_MLFLOW_PORT:-55000}"
HOST="$(hostname -s)"
SLURM_CONF_FILE="$DIR/slurm/slurm.conf"
MLFLOW_URI="http://127.0.0.1:$MLFLOW_PORT"

say() { echo "local_cluster: $*" >&2; }
die() { say "error: $*"; exit 1; }

install() {
  [ "$(id -u)" = 0 ] || die "install needs root (apt-get)"
  if ! command -v slurmctld >/dev/null || ! command -v munged >/dev/null || [ -z "$PG_BIN" ]; then
    DEBIAN_FRONTEND=noninteractive apt-get install -y -q slurm-wlm munge postgresql >/dev/null 2>&1 || {
      apt-get update -q >/dev/null 2>&1 &&
        DEBIAN_FRONTEND=noninteractive apt-get install -y -q slurm-wlm munge postgresql >/dev/null 2>&1; } ||
      die "apt-get install slurm-wlm munge postgresql failed"
  fi
}

write_slurm_conf() {
  local cpus mem
  cpus="$(nproc)"
  mem="$(( $(awk '/MemTotal/ {print $2}' /proc/meminfo) / 1024 - 2048 ))"
  mkdir -p "$DIR/slurm/state" "$DIR/slurm/spool" "$DIR/slurm/log"
  cat > "$SLURM_CONF_FILE" <<CONF
# written by cluster/local_cluster.sh: one node, no accounting database (status via squeue; MinJobAge keeps
# finished jobs visible long enough for Snakemake's status checks)
ClusterName=avatarlab
SlurmctldHost=$HOST
AuthType=auth/munge
CredType=cred/munge
SlurmUser=root
SlurmdUser=root
StateSaveLocation=$DIR/slurm/state
SlurmdSpoolDir=$DIR/slurm/spool
SlurmctldPidFile=$DIR/slurm/slurmctld.pid
SlurmdPidFile=$DIR/slurm/slurmd.pid
SlurmctldLogFile=$DIR/slurm/log/slurmctld.log
SlurmdLogFile=$DIR/slurm/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
SchedulerType=sched/backfill
MpiDefault=none
ReturnToService=2
MinJobAge=3600
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
NodeName=$HOST CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=main Nodes=$HOST Default=YES MaxTime=INFINITE State=UP
CONF
  # srun inside a job finds the configuration only at the default path (the job environment drops SLURM_CONF)
  mkdir -p /etc/slurm
  if [ -e /etc/slurm/slurm.conf ] && [ "$(readlink -f /etc/slurm/slurm.conf)" != "$SLURM_CONF_FILE" ]; then
    grep -q "written by cluster/local_cluster.sh" /etc/slurm/slurm.conf ||
      die "/etc/slurm/slurm.conf exists and is not ours: this script is for a machine without SLURM of its own"
  fi
  ln -sf "$SLURM_CONF_FILE" /etc/slurm/slurm.conf
}

start_slurm() {
  export SLURM_CONF="$SLURM_CONF_FILE"
  if scontrol ping 2>/dev/null | grep -q UP; then say "slurm already up"; return; fi
  write_slurm_conf
  mkdir -p /run/munge && chown munge:munge /run/munge 2>/dev/null || true
  [ -s /etc/munge/munge.key ] || { dd if=/dev/urandom bs=1 count=1024 of=/etc/munge/munge.key 2>/dev/null;
                                    chown munge:munge /etc/munge/munge.key; chmod 400 /etc/munge/munge.key; }
  pgrep -x munged >/dev/null || runuser -u munge -- munged || munged --force || die "munged did not start"
  slurmctld -f "$SLURM_CONF_FILE" || die "slurmctld did not start (see $DIR/slurm/log/slurmctld.log)"
  slurmd -f "$SLURM_CONF_FILE" || die "slurmd did not start (see $DIR/slurm/log/slurmd.log)"
  for _ in $(seq 60); do
    sinfo -h -o %T 2>/dev/null | grep -qE '^idle' && { say "slurm up: $(sinfo -h -o '%P %D %c cpus %m MB %T')"; return; }
    sleep 1
  done
  die "the SLURM node did not become idle (see $DIR/slurm/log/)"
}

start_postgres() {
  [ -n "$PG_BIN" ] || die "PostgreSQL is not installed (run: $0 install)"
  local data="$DIR/postgres/data"
  mkdir -p "$DIR/postgres" && chown postgres "$DIR/postgres"
  if [ ! -s "$data/PG_VERSION" ]; then
    runuser -u postgres -- "$PG_BIN/initdb" -D "$data" -A trust -U postgres >/dev/null || die "initdb failed"
  fi
  if ! runuser -u postgres -- "$PG_BIN/pg_ctl" -D "$data" status >/dev/null 2>&1; then
    runuser -u postgres -- "$PG_BIN/pg_ctl" -D "$data" -l "$DIR/postgres/server.log" -w \
      -o "-p $PG_PORT -k $DIR/postgres -c listen_addresses=127.0.0.1 -c max_connections=200" start >/dev/null ||
      die "PostgreSQL did not start (see $DIR/postgres/server.log)"
  fi
  "$PG_BIN/psql" -h 127.0.0.1 -p "$PG_PORT" -U postgres -tAc "SELECT 1 FROM pg_database WHERE datname='mlflow'" |
    grep -q 1 || "$PG_BIN/createdb" -h 127.0.0.1 -p "$PG_PORT" -U postgres mlflow
  say "postgres up on 127.0.0.1:$PG_PORT (database mlflow)"
}

start_mlflow() {
  if curl -sf "$MLFLOW_URI/health" >/dev/null 2>&1; then say "mlflow already up at $MLFLOW_URI"; return; fi
  mkdir -p "$DIR/mlflow/artifacts"
  nohup "$PYTHON" -m mlflow server --host 127.0.0.1 --port "$MLFLOW_PORT" --workers 2 \
    --backend-store-uri "postgresql://postgres@127.0.0.1:$PG_PORT/mlflow" \
    --artifacts-destination "$DIR/mlflow/artifacts" --serve-artifacts \
    > "$DIR/mlflow/server.log" 2>&1 &
  echo $! > "$DIR/mlflow/server.pid"
  for _ in $(seq 120); do
    curl -sf "$MLFLOW_URI/health" >/dev/null 2>&1 && { say "mlflow up at $MLFLOW_URI (PostgreSQL store)"; return; }
    kill -0 "$(cat "$DIR/mlflow/server.pid")" 2>/dev/null || die "mlflow server exited (see $DIR/mlflow/server.log)"
    sleep 1
  done
  die "mlflow server did not answer (see $DIR/mlflow/server.log)"
}

print_env() {
  echo "export SLURM_CONF=$SLURM_CONF_FILE"
  echo "export MLFLOW_TRACKING_URI=$MLFLOW_URI"
}

down() {
  [ -f "$DIR/mlflow/server.pid" ] && { pkill -P "$(cat "$DIR/mlflow/server.pid")" 2>/dev/null || true;
                                       kill "$(cat "$DIR/mlflow/server.pid")" 2>/dev/null || true; rm -f "$DIR/mlflow/server.pid"; }
  [ -n "$PG_BIN" ] && [ -d "$DIR/postgres/data" ] &&
    runuser -u postgres -- "$PG_BIN/pg_ctl" -D "$DIR/postgres/data" -m fast stop >/dev/null 2>&1 || true
  for pidfile in "$DIR/slurm/slurmd.pid" "$DIR/slurm/slurmctld.pid"; do
    [ -f "$pidfile" ] && kill "$(cat "$pidfile")" 2>/dev/null || true
  done
  say "stopped"
}

status() {
  SLURM_CONF="$SLURM_CONF_FILE" sinfo 2>&1 || true
  curl -sf "$MLFLOW_URI/health" && echo " mlflow $MLFLOW_URI" || echo "mlflow: down"
}

case "${1:-}" in
  install) install ;;
  up) mkdir -p "$DIR"; start_slurm; start_postgres; start_mlflow; print_env ;;
  slurm) mkdir -p "$DIR"; start_slurm; print_env ;;
  tracking) mkdir -p "$DIR"; start_postgres; start_mlflow; print_env ;;
  env) print_env ;;
  down) down ;;
  status) status ;;
  *) echo "usage: $0 install|up|slurm|tracking|env|down|status" >&2; exit 2 ;;
esac
