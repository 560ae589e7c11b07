#!/usr/bin/env bash
# A one-node Slurm cluster on this machine, for the tests that submit sharded builds to a
# real scheduler (docs/SHARDS.md, "Under a batch scheduler").
#
#   slurm-local.sh start    write a configuration, start munged, slurmctld and slurmd,
#                           wait until the node is idle; prints `export SLURM_CONF=…`
#   slurm-local.sh status   whether its daemons run and what the node's state is
#   slurm-local.sh stop     stop the daemons by their own process ids
#
# Installs nothing (tools/scripts/setup.sh installs slurm-wlm and munge from Debian and
# starts no service). Everything lives under SLURM_LOCAL_DIR (default
# ${TMPDIR:-/tmp}/citystream-slurm): configuration, munge key and socket, state, spool,
# logs and process ids. No cgroups and no systemd (proctrack/linuxproc, task/none); the
# node has this machine's cores and memory. Ports: SLURM_LOCAL_PORT and the one after it
# (default 6817, 6818). Clients (sbatch, squeue, scontrol) need SLURM_CONF set to the
# printed file.
set -euo pipefail

DIR=${SLURM_LOCAL_DIR:-${TMPDIR:-/tmp}/citystream-slurm}
PORT=${SLURM_LOCAL_PORT:-6817}
CONF=$DIR/etc/slurm.conf
NODE=$(hostname -s)

say() { printf '[slurm-local] %s\n' "$*" >&2; }
fail() {
    printf '[slurm-local] ERROR: %s\n' "$*" >&2
    exit 1
}

need() {
    local tool
    for tool in munged mungekey slurmctld slurmd sinfo sbatch; do
        command -v "$tool" >/dev/null || fail "$tool is not installed: run tools/scripts/setup.sh (it installs slurm-wlm and munge)"
    done
}

pid_of() {
    local file=$DIR/run/$1.pid
    [[ -f $file ]] || return 1
    local pid
    pid=$(<"$file")
    [[ $pid =~ ^[0-9]+$ ]] && kill -0 "$pid" 2>/dev/null && printf '%s' "$pid"
}

write_config() {
    mkdir -p "$DIR"/{etc,run,log,state,spool,munge}
    chmod 700 "$DIR/munge"
    local cpus memory_mb
    cpus=$(nproc)
    memory_mb=$(awk '/^MemTotal:/ {print int($2 / 1024 * 0.9)}' /proc/meminfo)
    cat >"$CONF" <<CONF
# Written by tools/scripts/slurm-local.sh: a one-node cluster for citystream's tests.
ClusterName=citystream-local
SlurmctldHost=$NODE
SlurmctldPort=$PORT
SlurmdPort=$((PORT + 1))
SlurmUser=$(id -un)
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$DIR/munge/munge.socket
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
MpiDefault=none
ReturnToService=2
SlurmctldTimeout=30
SlurmdTimeout=30
InactiveLimit=0
KillWait=5
MinJobAge=300
StateSaveLocation=$DIR/state
SlurmdSpoolDir=$DIR/spool
SlurmctldPidFile=$DIR/run/slurmctld.pid
SlurmdPidFile=$DIR/run/slurmd.pid
SlurmctldLogFile=$DIR/log/slurmctld.log
SlurmdLogFile=$DIR/log/slurmd.log
NodeName=$NODE CPUs=$cpus RealMemory=$memory_mb State=UNKNOWN
PartitionName=local Nodes=$NODE Default=YES MaxTime=INFINITE State=UP OverSubscribe=YES
CONF
}

start() {
    need
    if pid_of slurmctld >/dev/null && pid_of slurmd >/dev/null && pid_of munged >/dev/null; then
        say "already running under $DIR"
        printf 'export SLURM_CONF=%s\n' "$CONF"
        return 0
    fi
    stop_daemons
    write_config
    [[ -f $DIR/munge/munge.key ]] || mungekey --create --keyfile="$DIR/munge/munge.key" >/dev/null
    chmod 400 "$DIR/munge/munge.key"
    munged --force --key-file="$DIR/munge/munge.key" --socket="$DIR/munge/munge.socket" \
        --pid-file="$DIR/run/munged.pid" --log-file="$DIR/log/munged.log" \
        --seed-file="$DIR/munge/munged.seed" ||
        fail "munged did not start ($DIR/log/munged.log)"
    export SLURM_CONF=$CONF
    # -i: ignore state a previous cluster in this directory left (jobs, node states).
    slurmctld -f "$CONF" -i || fail "slurmctld did not start ($DIR/log/slurmctld.log)"
    slurmd -f "$CONF" || fail "slurmd did not start ($DIR/log/slurmd.log)"
    local waited=0 state=""
    while ((waited < 60)); do
        state=$(sinfo -h -n "$NODE" -o '%T' 2>/dev/null | head -n1 || true)
        [[ $state == idle || $state == mixed ]] && break
        sleep 1
        waited=$((waited + 1))
    done
    if [[ $state != idle && $state != mixed ]]; then
        fail "the node is '${state:-unknown}' after 60 s, not idle (logs in $DIR/log)"
    fi
    say "one-node cluster up under $DIR: node $NODE idle after ${waited} s"
    printf 'export SLURM_CONF=%s\n' "$CONF"
}

stop_daemons() {
    local daemon pid
    for daemon in slurmd slurmctld munged; do
        if pid=$(pid_of "$daemon"); then
            kill "$pid" 2>/dev/null || true
            for _ in $(seq 50); do
                kill -0 "$pid" 2>/dev/null || break
                sleep 0.1
            done
            kill -9 "$pid" 2>/dev/null || true
        fi
        rm -f "$DIR/run/$daemon.pid"
    done
}

status() {
    local daemon pid up=0
    for daemon in munged slurmctld slurmd; do
        if pid=$(pid_of "$daemon"); then
            say "$daemon running (pid $pid)"
            up=$((up + 1))
        else
            say "$daemon not running"
        fi
    done
    if ((up == 3)); then
        SLURM_CONF=$CONF sinfo -h -n "$NODE" -o "node %N: %T, %c CPUs" >&2 || true
        return 0
    fi
    return 1
}

case ${1:-} in
start) start ;;
stop)
    stop_daemons
    say "stopped"
    ;;
status) status ;;
*)
    printf 'usage: %s start|stop|status\n' "$0" >&2
    exit 2
    ;;
esac
