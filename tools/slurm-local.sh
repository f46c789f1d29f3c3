#!/usr/bin/env bash
# Starts a real single-node Slurm cluster on this machine (slurmctld + slurmd + munge), for the farm test (tools/farm/slurm-batch.sh).
# A real single-node Slurm cluster on this machine, for testing farm use (array jobs) for real.
#   slurm-local.sh start   install (Debian's slurm-wlm + munge) if needed, configure, start; waits until idle
#   slurm-local.sh stop    stop the daemons it started
#   slurm-local.sh status  sinfo
# Needs root (apt-get, daemons). State lives in $SLURM_LOCAL_DIR (default: a folder under $TMPDIR or /tmp).
set -euo pipefail
D="${SLURM_LOCAL_DIR:-${TMPDIR:-/tmp}/slurm-local}"
H=$(hostname -s)
start() {
  if ! command -v slurmctld >/dev/null || ! command -v munged >/dev/null; then
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq slurm-wlm munge >/dev/null
  fi
  mkdir -p "$D"/{state,spool,log} /run/munge /var/log/munge /var/lib/munge /etc/munge
  [ -s /etc/munge/munge.key ] || head -c 1024 /dev/urandom >/etc/munge/munge.key
  chown -R munge:munge /etc/munge /run/munge /var/log/munge /var/lib/munge
  chmod 700 /etc/munge; chmod 400 /etc/munge/munge.key
  if ! munge -n >/dev/null 2>&1; then
    /usr/sbin/munged --force 2>/dev/null; sleep 0.5; pgrep -n -x munged >"$D/munged.pid"
  fi
  cat >/etc/slurm/slurm.conf <<CONF
ClusterName=local
SlurmctldHost=$H
SlurmUser=root
SlurmdUser=root
StateSaveLocation=$D/state
SlurmdSpoolDir=$D/spool
SlurmctldPidFile=$D/slurmctld.pid
SlurmdPidFile=$D/slurmd.pid
SlurmctldLogFile=$D/log/slurmctld.log
SlurmdLogFile=$D/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
ReturnToService=2
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
AuthType=auth/munge
NodeName=$H CPUs=$(nproc) RealMemory=$(( $(awk '/MemTotal/{print int($2/1024)}' /proc/meminfo) * 8 / 10 )) State=UNKNOWN
PartitionName=main Nodes=$H Default=YES MaxTime=INFINITE State=UP
CONF
  printf 'CgroupPlugin=cgroup/v1\nCgroupAutomount=no\nIgnoreSystemd=yes\n' >/etc/slurm/cgroup.conf
  [ -f "$D/slurmctld.pid" ] && kill -0 "$(cat "$D/slurmctld.pid")" 2>/dev/null || /usr/sbin/slurmctld
  [ -f "$D/slurmd.pid" ] && kill -0 "$(cat "$D/slurmd.pid")" 2>/dev/null || /usr/sbin/slurmd
  for _ in $(seq 60); do sinfo -h -o %T 2>/dev/null | grep -q idle && { sinfo; return 0; }; sleep 1; done
  echo "slurm did not become idle; see $D/log" >&2; return 1
}
stop() {
  for p in "$D/slurmd.pid" "$D/slurmctld.pid" "$D/munged.pid"; do
    [ -f "$p" ] && kill "$(cat "$p")" 2>/dev/null || true
  done
  rm -f "$D/munged.pid"
}
case "${1:-}" in start) start ;; stop) stop ;; status) sinfo ;; *) echo "usage: $0 start|stop|status" >&2; exit 2 ;; esac
