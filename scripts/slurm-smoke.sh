#!/usr/bin/env bash
# SLURM smoke test of profiles/slurm (issue 8, part 5).
#
# Installs a single-node SLURM from Debian packages (slurmctld, slurmd, slurm-client,
# munge) and snakemake-executor-plugin-slurm (envs/requirements-slurm.txt) on this
# machine, starts a private munged + slurmctld + slurmd (key, socket, state and logs under
# $SLURM_SMOKE_ROOT; ports 16817/16818, not SLURM's defaults; the config goes to SLURM's
# default place /etc/slurm/slurm.conf, as on a cluster, and only if no other SLURM config
# is there: it is marked as ours and removed again at the end), checks them
# with sinfo / srun, runs the tiny garment scene (scripts/slurm/tiny.yaml) through
# `snakemake --executor slurm` with the slurm profile, and checks
#   - every planned job ran as one SLURM job that ended COMPLETED with exit 0:0,
#   - SLURM granted what the profile asks: runtime -> TimeLimit, mem_mb -> --mem,
#     cpus_per_task -> CPUs/Task, gpu -> --gpus (one rule asks for the fake GPU),
#   - the outputs hold their contract (dataset, template, simulations, rig, logs, benchmarks),
# then runs the same targets locally (the reference) and writes benchmarks/slurm.{md,csv}.
# Daemons are stopped at the end (also on failure) unless --keep.
#
# usage: sudo scripts/slurm-smoke.sh [--keep] [--stop] [--no-install] [--no-reference]
#                                    [--report PATH_WITHOUT_SUFFIX] [TARGET ...]
#   --keep          leave munged, slurmctld and slurmd running (and /etc/slurm/slurm.conf)
#   --stop          only stop the daemons a previous --keep left running
#   --no-install    do not apt-get / pip install (fail if something is missing)
#   --no-reference  skip the local reference run
#   TARGET ...      snakemake targets (default: data/tinyskirt results/tinyskirt/rig.npz,
#                   i.e. synth, template, motions x2, simulate x2, rig)
# env: SLURM_SMOKE_ROOT (default /tmp/anidress-slurm-smoke), PYTHON (default .venv/bin/python),
#      SLURM_SMOKE_CTLD_PORT / SLURM_SMOKE_SLURMD_PORT (default 16817 / 16818)
# exit status: 0 when every check passes.
set -euo pipefail

REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
ROOT=${SLURM_SMOKE_ROOT:-/tmp/anidress-slurm-smoke}
PY=${PYTHON:-$REPO/.venv/bin/python}
CTLD_PORT=${SLURM_SMOKE_CTLD_PORT:-16817}
SLURMD_PORT=${SLURM_SMOKE_SLURMD_PORT:-16818}
KEEP=0 STOP_ONLY=0 INSTALL=1 REFERENCE=1
REPORT=$REPO/benchmarks/slurm
TARGETS=()
COMMAND="scripts/slurm-smoke.sh${*:+ $*}"

while [[ $# -gt 0 ]]; do
    case $1 in
        --keep) KEEP=1 ;;
        --stop) STOP_ONLY=1 ;;
        --no-install) INSTALL=0 ;;
        --no-reference) REFERENCE=0 ;;
        --report) REPORT=$2; shift ;;
        -h|--help) sed -n '2,/^set -euo/p' "$0" | sed '$d' | sed 's/^# \{0,1\}//'; exit 0 ;;
        -*) echo "slurm-smoke: unknown option $1 (see --help)" >&2; exit 2 ;;
        *) TARGETS+=("$1") ;;
    esac
    shift
done
[[ ${#TARGETS[@]} -gt 0 ]] || TARGETS=(data/tinyskirt results/tinyskirt/rig.npz)

log() { echo "[slurm-smoke $(date +%T)] $*" >&2; }
die() { log "ERROR: $*"; exit 1; }

[[ $EUID -eq 0 ]] || die "needs root: it installs Debian packages and starts munged, slurmctld and slurmd (run: sudo $0)"

# The config lives where SLURM looks by default: the job steps that
# snakemake-executor-plugin-slurm-jobstep 0.6.1 starts with srun drop SLURM_CONF from
# their environment, so a config found only through SLURM_CONF would not reach them.
CONF_DIR=/etc/slurm
MARKER="# Written by AniDress scripts/slurm-smoke.sh"
unset SLURM_CONF
MUNGE_SOCKET=$ROOT/munge/munge.socket

# -- stop the daemons this script started (pid files under $ROOT, process name checked) --
stop_pid() {  # stop_pid NAME PIDFILE
    local name=$1 pidfile=$2 pid
    [[ -f $pidfile ]] || return 0
    pid=$(cat "$pidfile" 2>/dev/null || true)
    if [[ -n $pid && -d /proc/$pid && $(cat /proc/"$pid"/comm 2>/dev/null) == "$name" ]]; then
        kill "$pid" 2>/dev/null || true
        for _ in $(seq 50); do [[ -d /proc/$pid ]] || break; sleep 0.2; done
        if [[ -d /proc/$pid ]]; then log "$name ($pid) did not stop on TERM, sending KILL"; kill -9 "$pid" 2>/dev/null || true; fi
        log "stopped $name ($pid)"
    fi
    rm -f "$pidfile"
}
ours() { [[ -f $1 ]] && [[ $(head -n 1 "$1") == "$MARKER"* ]]; }
stop_daemons() {
    stop_pid slurmd "$ROOT/run/slurmd.pid"
    stop_pid slurmctld "$ROOT/run/slurmctld.pid"
    stop_pid munged "$ROOT/munge/munged.pid"
    local f
    for f in "$CONF_DIR/slurm.conf" "$CONF_DIR/gres.conf"; do
        if ours "$f"; then rm -f "$f"; fi
    done
}

if [[ $STOP_ONLY -eq 1 ]]; then stop_daemons; exit 0; fi

# -- 1. packages -------------------------------------------------------------------------
if [[ $INSTALL -eq 1 ]]; then
    if ! command -v slurmctld >/dev/null || ! command -v slurmd >/dev/null || ! command -v sbatch >/dev/null \
        || ! command -v munged >/dev/null || ! command -v mungekey >/dev/null; then
        log "installing slurmctld slurmd slurm-client munge (apt-get)"
        apt-get update -qq
        DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends \
            slurmctld slurmd slurm-client munge >/dev/null
    fi
    [[ -x $PY ]] || die "$PY not found: run \`make venv\` first (or set PYTHON)"
    log "pip install -r envs/requirements-slurm.txt"
    "$PY" -m pip install --disable-pip-version-check -q -r "$REPO/envs/requirements-slurm.txt"
fi
for exe in slurmctld slurmd sbatch sinfo srun squeue scontrol munged mungekey munge unmunge; do
    command -v "$exe" >/dev/null || die "$exe not found (Debian: apt-get install slurmctld slurmd slurm-client munge)"
done
"$PY" -c "import snakemake_executor_plugin_slurm" 2>/dev/null \
    || die "snakemake-executor-plugin-slurm is not installed in $PY (pip install -r envs/requirements-slurm.txt)"

# -- 2. configuration (fresh state every run: idempotent) ----------------------------------
stop_daemons
trap '[[ $KEEP -eq 1 ]] || stop_daemons' EXIT
for f in "$CONF_DIR/slurm.conf" "$CONF_DIR/gres.conf"; do
    [[ ! -e $f ]] || ours "$f" || die "$f exists and was not written by this script: a SLURM installation is configured on this machine; not touching it"
done
mkdir -p "$ROOT"/{run,log,munge} "$CONF_DIR"
rm -rf "$ROOT"/spool "$ROOT"/log/*
mkdir -p "$ROOT"/spool/{ctld,d}
chmod 755 "$ROOT/munge"
if [[ ! -s $ROOT/munge/munge.key ]]; then mungekey --create --keyfile="$ROOT/munge/munge.key"; fi
chmod 400 "$ROOT/munge/munge.key"
read -r NODE_CPUS NODE_MEM < <("$PY" "$REPO/scripts/slurm/smoke.py" node "$REPO/profiles/slurm/config.yaml")
{ echo "$MARKER (state in $ROOT); removed when the smoke test stops"
  sed -e "s#@ROOT@#$ROOT#g" -e "s#@CTLD_PORT@#$CTLD_PORT#g" -e "s#@SLURMD_PORT@#$SLURMD_PORT#g" \
      -e "s#@CPUS@#$NODE_CPUS#g" -e "s#@MEM_MB@#$NODE_MEM#g" "$REPO/scripts/slurm/slurm.conf.in"; } >"$CONF_DIR/slurm.conf"
{ echo "$MARKER"; cat "$REPO/scripts/slurm/gres.conf.in"; } >"$CONF_DIR/gres.conf"
log "node: CPUs=$NODE_CPUS RealMemory=$NODE_MEM MB (machine: $(nproc) CPUs), config $CONF_DIR/slurm.conf"

# -- 3. daemons ------------------------------------------------------------------------------
munged --force --socket="$MUNGE_SOCKET" --key-file="$ROOT/munge/munge.key" --pid-file="$ROOT/munge/munged.pid" \
    --log-file="$ROOT/log/munged.log" --seed-file="$ROOT/munge/munged.seed"
for _ in $(seq 50); do [[ -S $MUNGE_SOCKET ]] && break; sleep 0.2; done
munge -S "$MUNGE_SOCKET" -n | unmunge -S "$MUNGE_SOCKET" >/dev/null || die "munge credential round trip failed (see $ROOT/log/munged.log)"
slurmctld -c || die "slurmctld did not start (see $ROOT/log/slurmctld.log)"
slurmd -c -N localhost || die "slurmd did not start (see $ROOT/log/slurmd.log)"
# a daemon is gone when its pid file, once written, names no process
alive() { [[ ! -f $1 ]] || [[ -d /proc/$(cat "$1" 2>/dev/null) ]]; }
state="" start=$SECONDS
while (( SECONDS - start < 90 )); do
    alive "$ROOT/run/slurmctld.pid" || { tail -n 20 "$ROOT/log/slurmctld.log" >&2; die "slurmctld exited (see $ROOT/log/slurmctld.log)"; }
    alive "$ROOT/run/slurmd.pid" || { tail -n 20 "$ROOT/log/slurmd.log" >&2; die "slurmd exited (see $ROOT/log/slurmd.log)"; }
    state=$(timeout 10 sinfo -h -N -n localhost -o %t 2>/dev/null || true)
    [[ $state == idle ]] && break
    # the first registration can race the controller's start: resume a node left drained/invalid
    if [[ $state == drain* || $state == inval* ]]; then
        scontrol update nodename=localhost state=resume 2>/dev/null || true
    fi
    sleep 2
done
[[ $state == idle ]] || { sinfo -N -l >&2 || true; tail -n 20 "$ROOT/log/slurmctld.log" "$ROOT/log/slurmd.log" >&2; die "node localhost is '$state', not idle after 90 s"; }
sinfo >&2
host=$(timeout 120 srun -N1 -n1 -t 1 --mem 100 hostname) || die "srun hostname failed"
log "srun hostname -> $host"
gpu_env=$(timeout 120 srun -N1 -n1 -t 1 --mem 100 --gpus=1 printenv CUDA_VISIBLE_DEVICES) || die "srun --gpus=1 failed"
log "srun --gpus=1 -> CUDA_VISIBLE_DEVICES=$gpu_env (fake GRES)"

# -- 4. the tiny scene through --executor slurm ------------------------------------------------
WORK=$ROOT/work
rm -rf "$WORK" && mkdir -p "$WORK"
cp "$REPO/scripts/slurm/tiny.yaml" "$WORK/tiny.yaml"
"$PY" "$REPO/scripts/slurm/smoke.py" profile "$REPO/profiles/slurm/config.yaml" "$WORK/profile"
SMK=("$PY" -m snakemake -s "$REPO/Snakefile" --directory "$WORK" --configfile "$WORK/tiny.yaml")
log "snakemake --profile $WORK/profile (executor slurm): ${TARGETS[*]}"
t0=$(date +%s.%N)
set +e
(cd "$WORK" && "${SMK[@]}" --workflow-profile none --profile "$WORK/profile" "${TARGETS[@]}") >"$WORK/snakemake-slurm.log" 2>&1
rc=$?
set -e
t1=$(date +%s.%N)
WALL_SLURM=$(awk -v a="$t0" -v b="$t1" 'BEGIN { printf "%.1f", b - a }')
grep -E "Submitted job|SLURM jobid|steps \(|Error|error" "$WORK/snakemake-slurm.log" | tail -n 30 >&2 || true
scontrol -o show job >"$WORK/scontrol-jobs.txt" 2>/dev/null || true
if [[ $rc -ne 0 ]]; then tail -n 60 "$WORK/snakemake-slurm.log" >&2; log "snakemake through SLURM failed (rc $rc); checking what is there"; fi
log "SLURM run: ${WALL_SLURM} s (rc $rc)"

# -- 5. local reference: the same targets without SLURM ----------------------------------------
REF_ARGS=()
if [[ $REFERENCE -eq 1 ]]; then
    REF=$ROOT/work-local
    rm -rf "$REF" && mkdir -p "$REF"
    cp "$REPO/scripts/slurm/tiny.yaml" "$REF/tiny.yaml"
    log "reference: local run of the same targets (default profile)"
    t0=$(date +%s.%N)
    (cd "$REF" && "$PY" -m snakemake -s "$REPO/Snakefile" --directory "$REF" --configfile "$REF/tiny.yaml" \
        --workflow-profile "$REPO/profiles/default" --cores "$(nproc)" "${TARGETS[@]}") >"$REF/snakemake-local.log" 2>&1 \
        || { tail -n 40 "$REF/snakemake-local.log" >&2; die "local reference run failed"; }
    t1=$(date +%s.%N)
    WALL_LOCAL=$(awk -v a="$t0" -v b="$t1" 'BEGIN { printf "%.1f", b - a }')
    log "local run: ${WALL_LOCAL} s"
    REF_ARGS=(--reference "$REF" --wall-local "$WALL_LOCAL")
fi

# -- 6. checks + benchmarks/slurm.{md,csv} -----------------------------------------------------
set +e
"$PY" "$REPO/scripts/slurm/smoke.py" check --work "$WORK" --profile "$WORK/profile/config.yaml" \
    --scontrol "$WORK/scontrol-jobs.txt" --targets "${TARGETS[@]}" --wall-slurm "$WALL_SLURM" "${REF_ARGS[@]}" \
    --node-cpus "$NODE_CPUS" --node-mem "$NODE_MEM" --command "$COMMAND" --report "$REPORT" >/dev/null
check_rc=$?
set -e
[[ $rc -eq 0 && $check_rc -eq 0 ]] && verdict=PASS || verdict=FAIL
log "$verdict: report in $REPORT.md and $REPORT.csv; logs in $ROOT/log, run in $WORK"
if [[ $KEEP -eq 1 ]]; then log "daemons left running (config $CONF_DIR/slurm.conf); stop them with $0 --stop"; fi
[[ $verdict == PASS ]]
