#!/usr/bin/env bash
# A real single-node Slurm for CI: installs slurm-wlm and munge from Debian's packages (as
# root), starts munged, slurmctld and slurmd from a temporary directory (no systemd), runs
# examples/slurm/ over the bundled IRIS sequences as 4 shards plus the merge, compares the
# merged log with a single-machine replay (tools/compare_shards.py), and stops the daemons
# by pid on exit, also when a step fails.
#
#   tools/ci/slurm.sh [SINGLE_RUN_DIR]
#
# SINGLE_RUN_DIR: an existing replay of the same inputs with examples/demo.toml (.ci/run
# passes ./demo.sh's); without it the single run is made here. Needs target/release/sunjitter
# (cargo build --release) and python3 with the `mcap` package.
set -euo pipefail
cd "$(dirname "$0")/../.."
root=$PWD
bin=${CARGO_TARGET_DIR:-$root/target}/release/sunjitter
shards=4
inputs=(
  "$root/data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits"
  "$root/data/real/iris_l2_20140329_140938_3860258481_SJI_2796_t000_deconvolved.fits"
)

if ! command -v slurmctld >/dev/null || ! command -v munged >/dev/null; then
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq
  apt-get install -y -qq --no-install-recommends slurm-wlm munge >/dev/null
fi
[[ -x $bin ]] || cargo build --release --quiet

tmp=$(mktemp -d /tmp/sunjitter-slurm.XXXXXX)
chmod 755 "$tmp"
pids=()
stop() {
  local code=$?
  # Reverse order of start: slurmd, slurmctld, munged; each by the pid it was started as.
  for ((i = ${#pids[@]} - 1; i >= 0; i--)); do
    kill "${pids[i]}" 2>/dev/null || true
  done
  for pid in "${pids[@]}"; do
    for _ in $(seq 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
    kill -9 "$pid" 2>/dev/null || true
  done
  if ((code != 0)); then
    for log in "$tmp"/*.log "$tmp"/run/*.out; do
      [[ -f $log ]] && { echo "--- $log"; tail -n 30 "$log"; }
    done >&2
  fi
  rm -rf "$tmp"
  exit "$code"
}
trap stop EXIT

# munge: its own key, socket and files in the temporary directory.
mkdir -m 700 "$tmp/munge"
dd if=/dev/urandom of="$tmp/munge/munge.key" bs=1024 count=1 status=none
chmod 400 "$tmp/munge/munge.key"
munged --force --foreground --key-file="$tmp/munge/munge.key" \
  --socket="$tmp/munge/munge.socket" --pid-file="$tmp/munge/munged.pid" \
  --log-file="$tmp/munged.log" --seed-file="$tmp/munge/munge.seed" 2>>"$tmp/munged.log" &
pids+=($!)
for _ in $(seq 100); do [[ -S $tmp/munge/munge.socket ]] && break; sleep 0.1; done
[[ -S $tmp/munge/munge.socket ]] || { echo "munged did not start" >&2; exit 1; }

host=$(hostname -s)
cpus=$(nproc)
mem=$(awk '/MemTotal/ {print int($2 / 1024 * 0.8)}' /proc/meminfo)
mkdir -p "$tmp/state" "$tmp/spool" "$tmp/run"
export SLURM_CONF=$tmp/slurm.conf
cat >"$SLURM_CONF" <<CONF
ClusterName=sunjitter-ci
SlurmctldHost=$host(127.0.0.1)
SlurmUser=root
SlurmdUser=root
SlurmctldPort=16817
SlurmdPort=16818
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$tmp/munge/munge.socket
StateSaveLocation=$tmp/state
SlurmdSpoolDir=$tmp/spool
SlurmctldPidFile=$tmp/slurmctld.pid
SlurmdPidFile=$tmp/slurmd.pid
SlurmctldLogFile=$tmp/slurmctld.log
SlurmdLogFile=$tmp/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
MpiDefault=none
ReturnToService=2
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
NodeName=$host NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=ci Nodes=$host Default=YES MaxTime=INFINITE State=UP
CONF
slurmctld -D -f "$SLURM_CONF" >>"$tmp/slurmctld.log" 2>&1 &
pids+=($!)
slurmd -D -f "$SLURM_CONF" >>"$tmp/slurmd.log" 2>&1 &
pids+=($!)
for _ in $(seq 150); do
  state=$(sinfo -h -n "$host" -o %t 2>/dev/null || true)
  [[ $state == idle ]] && break
  sleep 0.2
done
[[ $state == idle ]] || { echo "slurm node not idle (state: ${state:-none})" >&2; exit 1; }
echo "slurm: $(sinfo -h -o '%P %D %t %C') ($(sinfo -V))"

# The example as documented: a job array of the shards, the merge after it.
run=$tmp/run
export SUNJITTER=$bin SUNJITTER_CONFIG=$root/examples/demo.toml SUNJITTER_LOG=warn
started=$(date +%s)
array=$(sbatch --parsable --chdir="$run" --cpus-per-task=1 --mem=512M \
  --array=0-$((shards - 1)) examples/slurm/replay.sbatch "$shards" "$run" "${inputs[@]}")
sbatch --wait --chdir="$run" --mem=512M --dependency=afterok:"${array%%;*}" \
  examples/slurm/merge.sbatch "$shards" "$run" >/dev/null
echo "slurm: $shards shards and the merge took $(($(date +%s) - started)) s"

single=${1:-}
if [[ -z $single ]]; then
  single=$tmp/single
  "$bin" replay "${inputs[@]}" --config "$root/examples/demo.toml" --out "$single" 2>/dev/null
fi
python3 tools/compare_shards.py "$single" "$run/merged" --shards "$shards"
python3 tools/check_mcap.py "$run/merged" \
  --expect-count /jitter/SJI_1400=54 --expect-count /jitter/SJI_2796=72
