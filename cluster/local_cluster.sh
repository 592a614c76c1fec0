#!/usr/bin/env bash
# A one-machine "cluster" from Debian's packages, for the tests, CI and trying the cluster set-up before using a real
# one: SLURM (munged + slurmctld + slurmd, no accounting database) and an MLflow tracking server with a PostgreSQL
# backend store and a local artifact root. Everything lives in one private folder: $AVATARLAB_CLUSTER_DIR if set (it
# must be yours and not a symlink), otherwise a fresh `mktemp -d` folder whose path is kept in .local_cluster beside
# this repository. PostgreSQL accepts only scram-sha-256 password logins on 127.0.0.1; the random password is in
# <folder>/pgpass (mode 0600, read by libpq through PGPASSFILE). Outside the folder the script writes only what SLURM
# and munge need at their fixed paths: the /etc/slurm/slurm.conf symlink (removed again by `down`) and, if missing,
# /etc/munge/munge.key.
#
#   cluster/local_cluster.sh install   # apt-get the Debian packages (root) and pip the Python drivers into .venv
#   cluster/local_cluster.sh up        # start SLURM + PostgreSQL + MLflow; prints the environment to use
#   cluster/local_cluster.sh env       # the exports: SLURM_CONF, MLFLOW_TRACKING_URI, PGPASSFILE
#   cluster/local_cluster.sh down      # stop everything; a mktemp folder is removed, a given folder kept
#   cluster/local_cluster.sh status
set -euo pipefail

REPO="$(cd "$(dirname "$0")/.." && pwd)"
POINTER="$REPO/.local_cluster"
if [ -n "${AVATARLAB_CLUSTER_DIR:-}" ]; then
  DIR="$AVATARLAB_CLUSTER_DIR"; OWN_DIR=0
elif [ -f "$POINTER" ]; then
  DIR="$(cat "$POINTER")"; OWN_DIR=1
else
  DIR=""; OWN_DIR=1
fi
PYTHON="${PYTHON:-$REPO/.venv/bin/python}"
PG_BIN="$(ls -d /usr/lib/postgresql/*/bin 2>/dev/null | sort -V | tail -1)"
PG_PORT="${AVATARLAB_PG_PORT:-55432}"
MLFLOW_PORT="${AVATARLAB_MLFLOW_PORT:-55000}"
HOST="$(hostname -s)"
SLURM_CONF_FILE="${DIR:+$DIR/slurm/slurm.conf}"
MLFLOW_URI="http://127.0.0.1:$MLFLOW_PORT"

MARKER=".made-by-local_cluster"  # inside a folder this script made with mktemp: the only kind `down` removes
say() { echo "local_cluster: $*" >&2; }
die() { say "error: $*"; exit 1; }

# the private state folder: created with mktemp (or checked when given), 0711 so the postgres user can reach its
# own subfolder and nothing else
make_dir() {
  if [ -z "$DIR" ]; then
    DIR="$(mktemp -d /tmp/avatarlab-cluster.XXXXXXXX)"
    (umask 077; printf '%s\n' "$DIR" > "$DIR/$MARKER"; printf '%s\n' "$DIR" > "$POINTER")
  fi
  [ -L "$DIR" ] && die "$DIR is a symlink: give AVATARLAB_CLUSTER_DIR a real folder"
  mkdir -p "$DIR"
  [ -O "$DIR" ] || die "$DIR belongs to another user: give AVATARLAB_CLUSTER_DIR a folder of your own"
  chmod 0711 "$DIR"
  SLURM_CONF_FILE="$DIR/slurm/slurm.conf"
}

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
  (umask 077; mkdir -p "$DIR/slurm/state" "$DIR/slurm/spool" "$DIR/slurm/log")
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
  local data="$DIR/postgres/data" password pwfile
  (umask 077; mkdir -p "$DIR/postgres") && chown postgres "$DIR/postgres"
  if [ ! -s "$data/PG_VERSION" ]; then
    password="$(head -c 32 /dev/urandom | od -An -tx1 | tr -d ' \n')"
    pwfile="$DIR/postgres/initdb.pw"
    (umask 077; printf '%s\n' "$password" > "$pwfile") && chown postgres "$pwfile"
    (umask 077; printf '127.0.0.1:%s:*:postgres:%s\n' "$PG_PORT" "$password" > "$DIR/pgpass")
    runuser -u postgres -- "$PG_BIN/initdb" -D "$data" -A scram-sha-256 --pwfile="$pwfile" -U postgres >/dev/null ||
      { rm -f "$pwfile"; die "initdb failed"; }
    rm -f "$pwfile"
  fi
  export PGPASSFILE="$DIR/pgpass"
  if ! runuser -u postgres -- "$PG_BIN/pg_ctl" -D "$data" status >/dev/null 2>&1; then
    runuser -u postgres -- "$PG_BIN/pg_ctl" -D "$data" -l "$DIR/postgres/server.log" -w \
      -o "-p $PG_PORT -k $DIR/postgres -c listen_addresses=127.0.0.1 -c max_connections=200" start >/dev/null ||
      die "PostgreSQL did not start (see $DIR/postgres/server.log)"
  fi
  "$PG_BIN/psql" -w -h 127.0.0.1 -p "$PG_PORT" -U postgres -tAc "SELECT 1 FROM pg_database WHERE datname='mlflow'" |
    grep -q 1 || "$PG_BIN/createdb" -w -h 127.0.0.1 -p "$PG_PORT" -U postgres mlflow
  say "postgres up on 127.0.0.1:$PG_PORT (database mlflow)"
}

start_mlflow() {
  if curl -sf "$MLFLOW_URI/health" >/dev/null 2>&1; then say "mlflow already up at $MLFLOW_URI"; return; fi
  (umask 077; mkdir -p "$DIR/mlflow/artifacts")
  PGPASSFILE="$DIR/pgpass" MLFLOW_DISABLE_TELEMETRY=true DO_NOT_TRACK=true setsid nohup "$PYTHON" -m mlflow server --host 127.0.0.1 --port "$MLFLOW_PORT" --workers 2 \
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
  [ -n "$DIR" ] || die "no cluster folder: run '$0 up' first"
  echo "export SLURM_CONF=$SLURM_CONF_FILE"
  echo "export MLFLOW_TRACKING_URI=$MLFLOW_URI"
  echo "export PGPASSFILE=$DIR/pgpass"
}

# a folder `make_dir` made: a mktemp name under /tmp, a real folder of ours, holding the marker that names it
made_here() {
  case "$1" in /tmp/avatarlab-cluster.????????) ;; *) return 1 ;; esac
  [ -d "$1" ] && [ ! -L "$1" ] && [ -O "$1" ] && [ -f "$1/$MARKER" ] && [ "$(cat "$1/$MARKER")" = "$1" ]
}

down() {
  [ -n "$DIR" ] || { say "nothing to stop"; return; }
  # the server and its workers and job consumers: one process group (setsid)
  [ -f "$DIR/mlflow/server.pid" ] && { kill -- "-$(cat "$DIR/mlflow/server.pid")" 2>/dev/null || true;
                                       rm -f "$DIR/mlflow/server.pid"; }
  [ -n "$PG_BIN" ] && [ -d "$DIR/postgres/data" ] &&
    runuser -u postgres -- "$PG_BIN/pg_ctl" -D "$DIR/postgres/data" -m fast stop >/dev/null 2>&1 || true
  for pidfile in "$DIR/slurm/slurmd.pid" "$DIR/slurm/slurmctld.pid"; do
    [ -f "$pidfile" ] && kill "$(cat "$pidfile")" 2>/dev/null || true
  done
  [ "$(readlink /etc/slurm/slurm.conf 2>/dev/null)" = "$SLURM_CONF_FILE" ] && rm -f /etc/slurm/slurm.conf
  if [ "$OWN_DIR" = 1 ]; then
    made_here "$DIR" || die "$POINTER names $DIR, a folder this script did not make; nothing removed (delete \
$POINTER to forget it)"
    sleep 1; rm -rf -- "$DIR"; rm -f "$POINTER"; say "stopped; removed $DIR"
  else
    say "stopped (state kept in $DIR)"
  fi
}

status() {
  [ -n "$DIR" ] || { echo "local cluster: down (no folder)"; return; }
  SLURM_CONF="$SLURM_CONF_FILE" timeout 10 sinfo 2>&1 || true
  curl -sf "$MLFLOW_URI/health" && echo " mlflow $MLFLOW_URI" || echo "mlflow: down"
}

case "${1:-}" in
  install) install ;;
  up) make_dir; start_slurm; start_postgres; start_mlflow; print_env ;;
  slurm) make_dir; start_slurm; print_env ;;
  tracking) make_dir; start_postgres; start_mlflow; print_env ;;
  env) print_env ;;
  down) down ;;
  status) status ;;
  *) echo "usage: $0 install|up|slurm|tracking|env|down|status" >&2; exit 2 ;;
esac
