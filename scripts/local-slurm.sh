#!/usr/bin/env bash
# A real one-node SLURM cluster, with accounting, on this machine (Debian, as root).
#
#   bash scripts/local-slurm.sh          # install what is missing, start what is not running
#
# What it does, each step skipped when already done (safe to run again, e.g. by CI and then
# by hand; daemons already running are kept):
#   1. apt-get install slurm-wlm (slurmctld, slurmd, client commands), slurmdbd, mariadb-server
#      and munge, only when one of their programs is missing;
#   2. munge: a key and munged;
#   3. MariaDB: mysqld, the accounting database and its user;
#   4. slurmdbd: accounting storage. Snakemake's SLURM executor plugin follows its jobs with
#      sacct; without slurmdbd the jobs run but Snakemake never sees one finish;
#   5. slurmctld + slurmd with a minimal slurm.conf: one node (this machine's CPUs, 90 % of its
#      memory), one default partition "main", root as SlurmUser (no slurm system user needed);
#   6. account "default" with root in it, then a one-line job submitted and waited for, and
#      looked up with sacct: the check that the whole chain works.
# Quiet on success (one summary line); on any failure one clear message (plus the tail of the
# relevant log) on stderr and exit status 1. Every wait is bounded.
#
# Tested on Debian 12 (SLURM 22.05, MariaDB 10.11). Not for a real cluster: the database
# password is fixed and everything runs as root.
set -euo pipefail

CLUSTER=lfstudy
PARTITION=main
ACCOUNT=default
DB_NAME=slurm_acct_db
DB_USER=slurm
DB_PASS=lfstudy-local-slurm   # local socket/loopback only; a throw-away test cluster
LOGDIR=/var/log/lfstudy-slurm
STATE=/var/lib/lfstudy-slurm
CONF=/etc/slurm

die() {
    echo "local-slurm: error: $1" >&2
    if [[ -n "${2:-}" && -f "$2" ]]; then
        echo "--- last lines of $2:" >&2
        tail -n 20 "$2" >&2
    fi
    exit 1
}

# wait_for SECONDS WHAT COMMAND...: poll COMMAND every 0.5 s until it succeeds or time is up.
wait_for() {
    local limit=$1 what=$2
    shift 2
    local deadline=$((SECONDS + limit))
    until "$@" >/dev/null 2>&1; do
        ((SECONDS < deadline)) || return 1
        sleep 0.5
    done
}

running() { pgrep -x "$1" >/dev/null; }

[[ $(id -u) -eq 0 ]] || die "must run as root (it installs packages and starts system daemons)"
command -v apt-get >/dev/null || die "needs a Debian-like system with apt-get"
mkdir -p "$LOGDIR" "$STATE"

# 1. Packages -------------------------------------------------------------------------------
missing=0
for prog in sbatch sacct slurmctld slurmd slurmdbd munged mysqld; do
    command -v "$prog" >/dev/null || [[ -x /usr/sbin/$prog ]] || missing=1
done
if ((missing)); then
    # Package scripts must not try to start services (no init system in containers/CI).
    export DEBIAN_FRONTEND=noninteractive
    policy=/usr/sbin/policy-rc.d
    own_policy=0
    if [[ ! -e $policy ]]; then
        printf '#!/bin/sh\nexit 101\n' >"$policy" && chmod +x "$policy" && own_policy=1
    fi
    { timeout 300 apt-get update -q && timeout 1200 apt-get install -y -q --no-install-recommends \
        slurm-wlm slurmdbd mariadb-server munge; } >"$LOGDIR/apt.log" 2>&1 ||
        { ((own_policy)) && rm -f "$policy"; die "installing the SLURM/MariaDB packages failed" "$LOGDIR/apt.log"; }
    ((own_policy)) && rm -f "$policy"
fi
export PATH=$PATH:/usr/sbin:/sbin

# 2. munge -----------------------------------------------------------------------------------
if [[ ! -s /etc/munge/munge.key ]]; then
    mkdir -p /etc/munge
    dd if=/dev/urandom of=/etc/munge/munge.key bs=1024 count=1 status=none
fi
chown munge:munge /etc/munge/munge.key
chmod 400 /etc/munge/munge.key
mkdir -p /run/munge /var/log/munge /var/lib/munge
chown munge:munge /run/munge /var/log/munge /var/lib/munge
if ! running munged; then
    runuser -u munge -- munged >"$LOGDIR/munged.out" 2>&1 || die "munged did not start" "$LOGDIR/munged.out"
fi
wait_for 20 munge bash -c 'munge -n | unmunge' || die "munge credentials do not work" /var/log/munge/munged.log

# 3. MariaDB ----------------------------------------------------------------------------------
mkdir -p /run/mysqld /var/log/mysql && chown mysql:mysql /run/mysqld /var/log/mysql
if ! mysqladmin ping >/dev/null 2>&1; then
    [[ -d /var/lib/mysql/mysql ]] || mariadb-install-db --user=mysql >"$LOGDIR/mariadb-install.log" 2>&1 ||
        die "initialising the MariaDB data directory failed" "$LOGDIR/mariadb-install.log"
    # The error log must be writable by the mysql user.
    setsid mysqld_safe --user=mysql --log-error=/var/log/mysql/error.log </dev/null >"$LOGDIR/mysqld_safe.out" 2>&1 &
    wait_for 60 mysqld mysqladmin ping || die "MariaDB did not answer within 60 s" /var/log/mysql/error.log
fi
mysql -u root <<SQL >"$LOGDIR/mysql-setup.log" 2>&1 || die "creating the accounting database failed" "$LOGDIR/mysql-setup.log"
CREATE DATABASE IF NOT EXISTS $DB_NAME;
CREATE USER IF NOT EXISTS '$DB_USER'@'localhost' IDENTIFIED BY '$DB_PASS';
GRANT ALL ON $DB_NAME.* TO '$DB_USER'@'localhost';
SQL

# 4./5. Configuration --------------------------------------------------------------------------
# install_conf FILE MODE: put stdin at FILE if it differs; return 0 when it changed.
install_conf() {
    local tmp
    tmp=$(mktemp)
    cat >"$tmp"
    if [[ -f $1 ]] && cmp -s "$tmp" "$1"; then
        rm -f "$tmp"
        return 1
    fi
    install -m "$2" "$tmp" "$1"
    rm -f "$tmp"
}

mkdir -p "$CONF" "$STATE/ctld" "$STATE/d"
host=$(hostname -s)
cpus=$(nproc)
mem_mb=$(awk '/^MemTotal:/ {printf "%d", $2 / 1024 * 0.9}' /proc/meminfo)

changed=0
install_conf "$CONF/slurmdbd.conf" 600 <<EOF && changed=1 || true
# Written by lfstudy scripts/local-slurm.sh: accounting for a one-node test cluster.
AuthType=auth/munge
DbdHost=localhost
SlurmUser=root
LogFile=$LOGDIR/slurmdbd.log
PidFile=/run/slurmdbd.pid
StorageType=accounting_storage/mysql
StorageHost=localhost
StorageUser=$DB_USER
StoragePass=$DB_PASS
StorageLoc=$DB_NAME
EOF

install_conf "$CONF/slurm.conf" 644 <<EOF && changed=1 || true
# Written by lfstudy scripts/local-slurm.sh: a one-node cluster on this machine, all as root.
ClusterName=$CLUSTER
SlurmctldHost=$host(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=$STATE/ctld
SlurmdSpoolDir=$STATE/d
SlurmctldPidFile=/run/slurmctld.pid
SlurmdPidFile=/run/slurmd.pid
SlurmctldLogFile=$LOGDIR/slurmctld.log
SlurmdLogFile=$LOGDIR/slurmd.log
# No cgroups in containers: plain process tracking, no task binding.
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
# A node that was down (e.g. the machine rebooted) comes back by itself.
ReturnToService=2
# sacct (Snakemake's job status queries) reads slurmdbd; MaxRSS per job from /proc.
JobAcctGatherType=jobacct_gather/linux
JobAcctGatherFrequency=5
AccountingStorageType=accounting_storage/slurmdbd
AccountingStorageHost=localhost
# Short scheduling cycles: jobs of a test start at once.
SchedulerType=sched/backfill
SchedulerParameters=sched_min_interval=100000
MinJobAge=300
KillWait=5
InactiveLimit=0
NodeName=$host NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$mem_mb State=UNKNOWN
PartitionName=$PARTITION Nodes=$host Default=YES MaxTime=INFINITE State=UP
EOF

# A changed configuration (first run, or another machine size) restarts the daemons reading it.
stop() {
    local pid
    if pid=$(pgrep -x "$1"); then
        kill $pid
        wait_for 20 "$1 to stop" bash -c "! pgrep -x $1" || die "$1 did not stop within 20 s"
    fi
}
if ((changed)); then
    stop slurmd
    stop slurmctld
    stop slurmdbd
fi

# 4. slurmdbd ----------------------------------------------------------------------------------
if ! running slurmdbd; then
    slurmdbd >"$LOGDIR/slurmdbd.out" 2>&1 || die "slurmdbd did not start" "$LOGDIR/slurmdbd.log"
fi
wait_for 60 slurmdbd sacctmgr -n list cluster || die "slurmdbd did not answer within 60 s" "$LOGDIR/slurmdbd.log"
if [[ -z $(sacctmgr -n -P list cluster "$CLUSTER" format=cluster) ]]; then
    sacctmgr -i add cluster "$CLUSTER" >"$LOGDIR/sacctmgr.log" 2>&1 ||
        die "registering cluster $CLUSTER with slurmdbd failed" "$LOGDIR/sacctmgr.log"
fi

# 5. slurmctld, slurmd -------------------------------------------------------------------------
if ! running slurmctld; then
    slurmctld >"$LOGDIR/slurmctld.out" 2>&1 || die "slurmctld did not start" "$LOGDIR/slurmctld.log"
fi
wait_for 60 slurmctld bash -c 'scontrol ping | grep -q UP' || die "slurmctld did not answer within 60 s" "$LOGDIR/slurmctld.log"
if ! running slurmd; then
    slurmd >"$LOGDIR/slurmd.out" 2>&1 || die "slurmd did not start" "$LOGDIR/slurmd.log"
fi
node_ready() { sinfo -h -n "$host" -o %T | grep -qE '^(idle|mixed|allocated|completing)'; }
if ! wait_for 60 node node_ready; then
    # A node left down/drained by an earlier run (e.g. "Node unexpectedly rebooted").
    scontrol update nodename="$host" state=resume >/dev/null 2>&1 || true
    wait_for 30 node node_ready ||
        die "node $host is not usable: $(sinfo -h -n "$host" -o '%T %E')" "$LOGDIR/slurmd.log"
fi

# 6. Account, and one job end to end -----------------------------------------------------------
if [[ -z $(sacctmgr -n -P list account "$ACCOUNT" format=account) ]]; then
    sacctmgr -i add account "$ACCOUNT" Cluster="$CLUSTER" Description=lfstudy Organization=lfstudy \
        >>"$LOGDIR/sacctmgr.log" 2>&1 || die "adding account $ACCOUNT failed" "$LOGDIR/sacctmgr.log"
fi
if [[ -z $(sacctmgr -n -P list assoc user=root account="$ACCOUNT" format=user) ]]; then
    sacctmgr -i add user root Account="$ACCOUNT" Cluster="$CLUSTER" >>"$LOGDIR/sacctmgr.log" 2>&1 ||
        die "adding root to account $ACCOUNT failed" "$LOGDIR/sacctmgr.log"
fi

job=$(cd /tmp && timeout 120 sbatch --parsable --wait -A "$ACCOUNT" -p "$PARTITION" -t 1 -n 1 --mem=10 \
    -o /dev/null -J local-slurm-check --wrap true 2>"$LOGDIR/check.err") ||
    die "a test job did not complete within 120 s: $(sinfo -h -o '%n %T %E')" "$LOGDIR/check.err"
wait_for 30 sacct bash -c "sacct -n -X -j $job -o State | grep -q COMPLETED" ||
    die "sacct does not list test job $job as COMPLETED (slurmctld -> slurmdbd?)" "$LOGDIR/slurmctld.log"

echo "local-slurm: cluster '$CLUSTER' up: node $host ($cpus CPUs, $mem_mb MB), partition $PARTITION, account $ACCOUNT"
