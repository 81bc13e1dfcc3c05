#!/usr/bin/env bash
# A one-node Slurm on this machine for the Slurm tests (tests/flows/test_slurm.py; docs/clusters.md,
# "A Slurm for the tests"): Debian's slurm-wlm and munge, no systemd, no cgroups, no accounting.
#
#   infra/slurm/one-node.sh install   apt-get install slurm-wlm munge (root, Debian-like; once)
#   infra/slurm/one-node.sh start     start munged, slurmctld and slurmd; wait until the node is idle
#   infra/slurm/one-node.sh stop      stop the daemons this script started, by their pid files
#   infra/slurm/one-node.sh status    sinfo
#
# State, logs and pid files live in $BTF_SLURM_DIR (default /tmp/btf-slurm); job ids restart there
# at each start (its state folder is wiped). The node is `hostname -s` with every CPU and the memory
# less 1 GiB, in one partition `debug`. Slurm lets root submit; a non-root user needs the daemons
# started as root (sudo) once.
set -euo pipefail

S=${BTF_SLURM_DIR:-/tmp/btf-slurm}
CONF=/etc/slurm/slurm.conf

install_packages() {
    if command -v slurmctld >/dev/null 2>&1 && command -v munged >/dev/null 2>&1; then
        return 0
    fi
    [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1 || {
        echo "one-node.sh: installing Slurm needs root and apt-get" >&2; return 1; }
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq slurm-wlm munge >/dev/null
}

write_conf() {
    local host mem
    host=$(hostname -s)
    mem=$(( $(awk '/^MemTotal/ {print int($2 / 1024)}' /proc/meminfo) - 1024 ))
    mkdir -p /etc/slurm
    cat > "$CONF" <<CONF
# written by infra/slurm/one-node.sh: a one-node Slurm for the tests
ClusterName=btf-ci
SlurmctldHost=$host
SlurmUser=slurm
AuthType=auth/munge
CredType=cred/munge
MpiDefault=none
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
SchedulerType=sched/backfill
ReturnToService=2
SlurmctldPidFile=$S/slurmctld.pid
SlurmdPidFile=$S/slurmd.pid
StateSaveLocation=$S/state
SlurmdSpoolDir=$S/spool
SlurmctldLogFile=$S/log/slurmctld.log
SlurmdLogFile=$S/log/slurmd.log
NodeName=$host CPUs=$(nproc) RealMemory=$mem State=UNKNOWN
PartitionName=debug Nodes=ALL Default=YES MaxTime=INFINITE State=UP
CONF
}

start() {
    [ "$(id -u)" = 0 ] || { echo "one-node.sh: starting the Slurm daemons needs root" >&2; return 1; }
    command -v slurmctld >/dev/null 2>&1 || { echo "one-node.sh: Slurm is not installed (run: $0 install)" >&2; return 1; }
    if [ -s "$S/slurmctld.pid" ] && kill -0 "$(cat "$S/slurmctld.pid")" 2>/dev/null && sinfo -h >/dev/null 2>&1; then
        echo "one-node.sh: Slurm already runs (state in $S); left as it is"
        return 0
    fi
    if [ ! -s /etc/munge/munge.key ]; then
        mungekey --create --keyfile=/etc/munge/munge.key
        chown munge:munge /etc/munge/munge.key
        chmod 400 /etc/munge/munge.key
    fi
    install -d -o munge -g munge -m 755 /run/munge
    mkdir -p "$S"
    if ! munge -n 2>/dev/null | unmunge >/dev/null 2>&1; then
        runuser -u munge -- /usr/sbin/munged --pid-file=/run/munge/munged.pid
        cp /run/munge/munged.pid "$S/munged.pid"
    fi
    rm -rf "$S/state"
    install -d -o slurm -g slurm "$S/state" "$S/log"
    install -d "$S/spool"
    write_conf
    /usr/sbin/slurmctld
    /usr/sbin/slurmd
    for _ in $(seq 120); do
        if sinfo -h -o %t 2>/dev/null | grep -qx idle; then
            echo "one-node.sh: Slurm is up ($(sinfo -h -o '%P %D node(s) %c CPUs %m MB' | head -1); state in $S)"
            return 0
        fi
        sleep 0.5
    done
    echo "one-node.sh: the Slurm node did not become idle within 60 s; logs in $S/log" >&2
    return 1
}

stop() {
    # each daemon by the pid file this script's start wrote (never by name)
    local name pid
    for name in slurmd slurmctld munged; do
        [ -s "$S/$name.pid" ] || continue
        pid=$(cat "$S/$name.pid")
        if kill -0 "$pid" 2>/dev/null && grep -q "$name" "/proc/$pid/cmdline" 2>/dev/null; then
            kill "$pid"
            for _ in $(seq 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
        fi
        rm -f "$S/$name.pid"
    done
}

case "${1:-}" in
    install) install_packages ;;
    start) start ;;
    stop) stop ;;
    status) sinfo ;;
    *) echo "usage: $0 install|start|stop|status" >&2; exit 2 ;;
esac
