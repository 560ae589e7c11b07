#!/usr/bin/env bash
# The GPU check (docs/REAL_GPU.md): runs citystream's release binaries on whatever Vulkan
# device the machine has, within a time budget, and writes one summary.
#
# Made for a machine with a GPU and no package registry, network or Rust toolchain:
# `tools/scripts/gpu-check-pack.sh` (`make gpu-check-pack`) prepares, on a Debian 12 machine,
# the folder .gpu-check/ that travels with the working tree (release binaries, the Vulkan
# loader's and the validation layer's packages). It also runs on any machine with
# target/release built (lavapipe included), e.g. `GPU_CHECK_BUDGET_S=120 make gpu-check`.
#
# Steps, each timed and with its exit status; a step whose estimated time does not fit
# what remains of the budget is skipped, saying so:
#   0  preflight: binaries, Vulkan loader, driver and validation layer
#   1  device, driver, Vulkan version, each cache format's sparse block shape and mip
#      tail (the bind_cost bench prints them, then times binds)
#   2  the default city's standard path, sparse backing (--sparse on), validation with
#      synchronization validation and the bind checker: exit status, validation
#      messages, PSNR of the mean MSE against the fully resident reference
#   3  the `large` city at 1920x1080 and 3840x2160, culling on and off: GPU ms per pass,
#      wall ms per frame, meshes drawn; last, the `city` preset the same way if time allows
#   4  --clock real at 3840x2160 under a memory budget that makes the cache evict:
#      baseline, adaptive (the paper's controller) and adaptive (headroom): frame latency,
#      MB per path second, PSNR of the mean MSE; `citystream report` over the three
#   5  the bind_cost bench again (step 1's run stands for it when skipped)
#
# Writes into $OUT (default out/gpu-check), at most five files: gpu-check.json and
# gpu-check.md (the summary), gpu-check.log (this script's own lines), bind_cost.csv and
# gpu-check-runs.tar.gz (every step's log, summary.json, frames.csv and report). Scratch
# and datasets: out/gpu-check-work and data/. Exits 0 when every step that ran passed,
# 1 when one failed or ran past three times its estimate, 2 on a usage error; a step the
# end of the budget stopped is reported as out-of-budget, not as a failure.
#
# Environment:
#   GPU_CHECK_BUDGET_S      seconds the whole check may spend (default 540)
#   GPU_CHECK_STEPS         steps to run, comma-separated (default 1,2,3,4,5)
#   GPU_CHECK_PATH_S        camera seconds of step 2 (default: the whole standard path, 60)
#   GPU_CHECK_BENCH_S       camera seconds of each step-3 run (default 10)
#   GPU_CHECK_REAL_S        seconds of each step-4 run (default 20)
#   GPU_CHECK_EVICT_BUDGET_MB  step 4's memory budget (default 256 on `large`, 32 on the
#                           default city when `large` is not there)
#   GPU_CHECK_CITY_PRESET   auto (default: the `city` preset when time allows), 1 or 0
#   GPU_CHECK_BIND_LOG      1 (default): step 2 logs its binds (CITYSTREAM_BIND_LOG) and
#                           keeps the log when the step fails; 0: no log
#   GPU_CHECK_BIN           folder holding flythrough, citystream and bind_cost
#                           (default: .gpu-check/bin, else target/release)
#   GPU_CHECK_PACK          the packed folder (default .gpu-check)
#   GPU_CHECK_DATA          datasets (default data)
#   GPU_CHECK_WORK          scratch (default out/gpu-check-work; emptied at start; a folder
#                           with files the check did not make is refused)
#   GPU_CHECK_PYTHON        the summary's interpreter (default python3; none: without)
#   GPU_CHECK_CARRIED_LAYERS  1: use the carried validation layer even where one is
#                           installed (how to test the carried layer on lavapipe)
set -u
set -o pipefail

cd "$(dirname "${BASH_SOURCE[0]}")/../.." || exit 2
ROOT=$(pwd)

BUDGET_S=${GPU_CHECK_BUDGET_S:-540}
STEPS=${GPU_CHECK_STEPS:-1,2,3,4,5}
PATH_S=${GPU_CHECK_PATH_S:-}
BENCH_S=${GPU_CHECK_BENCH_S:-10}
REAL_S=${GPU_CHECK_REAL_S:-20}
EVICT_MB=${GPU_CHECK_EVICT_BUDGET_MB:-}
CITY_PRESET=${GPU_CHECK_CITY_PRESET:-auto}
BIND_LOG=${GPU_CHECK_BIND_LOG:-1}
PACK=${GPU_CHECK_PACK:-.gpu-check}
DATA=${GPU_CHECK_DATA:-data}
WORK=${GPU_CHECK_WORK:-out/gpu-check-work}
OUT_DIR=${OUT:-out/gpu-check}
# The summary's interpreter ("none": the plain summary gpu-check.sh writes itself).
PYTHON=${GPU_CHECK_PYTHON:-python3}
# Seconds kept back for the summary and the tarball.
RESERVE_S=20

usage_error() {
    printf 'gpu-check: %s\n' "$*" >&2
    exit 2
}
is_uint() { [[ $1 =~ ^[0-9]+$ ]]; }
is_secs() { [[ $1 =~ ^[0-9]+([.][0-9]+)?$ ]]; }
is_uint "$BUDGET_S" || usage_error "GPU_CHECK_BUDGET_S=$BUDGET_S is not a whole number of seconds"
[[ -z $PATH_S ]] || is_secs "$PATH_S" || usage_error "GPU_CHECK_PATH_S=$PATH_S is not a number of seconds"
is_secs "$BENCH_S" || usage_error "GPU_CHECK_BENCH_S=$BENCH_S is not a number of seconds"
is_secs "$REAL_S" || usage_error "GPU_CHECK_REAL_S=$REAL_S is not a number of seconds"
[[ -z $EVICT_MB ]] || is_uint "$EVICT_MB" || usage_error "GPU_CHECK_EVICT_BUDGET_MB=$EVICT_MB is not a whole number of MB"
[[ $STEPS =~ ^[1-5](,[1-5])*$ ]] || usage_error "GPU_CHECK_STEPS=$STEPS is not a comma-separated list of 1 to 5"
case $CITY_PRESET in auto | 0 | 1) ;; *) usage_error "GPU_CHECK_CITY_PRESET=$CITY_PRESET is not auto, 0 or 1" ;; esac

# The scratch folder is emptied on every run, so only one the check made itself (it holds
# this marker) or an empty one is taken: a folder with other files, such as the pack or a
# home directory, is refused untouched.
WORK_MARKER=.citystream-gpu-check-work
if [[ -d $WORK && ! -e $WORK/$WORK_MARKER && -n $(ls -A "$WORK" 2>/dev/null) ]]; then
    usage_error "GPU_CHECK_WORK=$WORK holds files this check did not make (no $WORK_MARKER in it); it empties its scratch folder on every run, so name a new or empty folder"
fi
mkdir -p "$OUT_DIR" "$WORK" || usage_error "cannot create $OUT_DIR or $WORK"
OUT_DIR=$(cd "$OUT_DIR" && pwd)
WORK=$(cd "$WORK" && pwd)
case $WORK in "$ROOT" | / | "$OUT_DIR") usage_error "GPU_CHECK_WORK=$WORK would empty a folder that is not scratch" ;; esac
: >"$WORK/$WORK_MARKER" || usage_error "cannot write $WORK/$WORK_MARKER"
rm -rf "${WORK:?}"/logs "${WORK:?}"/runs "${WORK:?}"/bin "${WORK:?}"/vk "$WORK/steps.tsv"
mkdir -p "$WORK/logs" "$WORK/runs" "$WORK/vk"
LOG=$OUT_DIR/gpu-check.log
: >"$LOG"
rm -f "$OUT_DIR/gpu-check.json" "$OUT_DIR/gpu-check.md" "$OUT_DIR/bind_cost.csv" "$OUT_DIR/gpu-check-runs.tar.gz"

now() { date +%s.%N; }
START=$(now)
elapsed() { awk -v a="$START" -v b="$(now)" 'BEGIN { printf "%.1f", b - a }'; }
remaining_s() { awk -v a="$START" -v b="$(now)" -v t="$BUDGET_S" 'BEGIN { r = t - (b - a); printf "%d", (r < 0 ? 0 : r) }'; }
say() { printf '[gpu-check %6ss] %s\n' "$(elapsed)" "$*" | tee -a "$LOG"; }
wants_step() { [[ ,$STEPS, == *,$1,* ]]; }

# --- step bookkeeping -------------------------------------------------------------------
# steps.tsv: one row per step or sub-step, read by tools/scripts/gpu-check-summary.py.
printf 'id\tstep\tkind\ttitle\tstate\trc\tseconds\testimate_s\trun_dir\tparams\tnote\n' >"$WORK/steps.tsv"
FAILED=0
# Fields are never empty ("-" stands for none): a tab-separated read would merge them.
clean_field() {
    local v
    v=$(printf '%s' "$1" | tr '\t\n\r' '   ')
    printf '%s' "${v:--}"
}
# record ID STEP KIND TITLE STATE RC SECONDS ESTIMATE RUN_DIR PARAMS NOTE
record() {
    local fields=() f
    for f in "$@"; do fields+=("$(clean_field "$f")"); done
    (
        IFS=$'\t'
        printf '%s\n' "${fields[*]}"
    ) >>"$WORK/steps.tsv"
    LAST_STATE=$5
    case $5 in failed | timed-out) FAILED=1 ;; esac
}
LAST_STATE=""

# Estimates: the GPU's figure, or lavapipe's (or any CPU device's) once step 1 saw one.
DEVICE_CLASS=gpu
# est GPU_BASE GPU_PER_S CPU_BASE CPU_PER_S [SECONDS]: base + per-second × seconds, whole s.
est() {
    local secs=${5:-0}
    if [[ $DEVICE_CLASS == cpu ]]; then
        awk -v b="$3" -v r="$4" -v s="$secs" 'BEGIN { printf "%d", b + r * s + 0.999 }'
    else
        awk -v b="$1" -v r="$2" -v s="$secs" 'BEGIN { printf "%d", b + r * s + 0.999 }'
    fi
}

# fits ESTIMATE: whether a step of that estimate fits what remains (less the reserve).
fits() { (($1 <= $(remaining_s) - RESERVE_S)); }

# run_step ID STEP KIND TITLE ESTIMATE RUN_DIR PARAMS -- COMMAND...
# Skips the step when its estimate does not fit; otherwise runs COMMAND with its output in
# logs/ID.log, stopped at three times its estimate or what remains, whichever is less.
# Returns COMMAND's status (3 when skipped).
run_step() {
    local id=$1 step=$2 kind=$3 title=$4 estimate=$5 run_dir=$6 params=$7
    shift 8
    local left
    left=$(remaining_s)
    if ! fits "$estimate"; then
        say "skip $id ($title): estimated ${estimate} s, ${left} s of the budget left (${RESERVE_S} s kept for the summary)"
        record "$id" "$step" "$kind" "$title" skipped "" 0 "$estimate" "$run_dir" "$params" \
            "estimated ${estimate} s, ${left} s left"
        return 3
    fi
    # Stopped at three times its estimate (a timeout: the step failed), or earlier where the
    # budget ends first (out of budget: recorded, not a failure).
    local limit=$((estimate * 3)) capped=0
    ((limit > left - RESERVE_S)) && limit=$((left - RESERVE_S)) capped=1
    ((limit < 1)) && limit=1
    say "run  $id ($title): estimated ${estimate} s, stopped after ${limit} s"
    local log="$WORK/logs/$id.log" t0 rc secs state note=""
    {
        printf '$'
        printf ' %q' "$@"
        printf '\n'
    } >"$log"
    t0=$(now)
    timeout --kill-after=15 "$limit" "$@" >>"$log" 2>&1 </dev/null
    rc=$?
    secs=$(awk -v a="$t0" -v b="$(now)" 'BEGIN { printf "%.1f", b - a }')
    case $rc in
        0) state=ok ;;
        124 | 137)
            if ((capped)); then
                state=out-of-budget note="stopped after ${limit} s, where the budget ends"
            else
                state=timed-out note="stopped after ${limit} s, three times its estimate"
            fi
            ;;
        *) state=failed note=$(grep -m1 -E '^(Error|error|thread .* panicked)' "$log" | cut -c1-300) ;;
    esac
    record "$id" "$step" "$kind" "$title" "$state" "$rc" "$secs" "$estimate" "$run_dir" "$params" "$note"
    say "     $id: $state (exit $rc) in ${secs} s${note:+: $note}"
    return "$rc"
}

# skip_step ID STEP KIND TITLE REASON: record a step that cannot run.
skip_step() {
    say "skip $1 ($4): $5"
    record "$1" "$2" "$3" "$4" skipped "" 0 "" "" "" "$5"
}

say "budget ${BUDGET_S} s; steps $STEPS; results in $OUT_DIR; scratch in $WORK"

# --- 0: preflight -----------------------------------------------------------------------
PRE_NOTES=()
PRE_T0=$(now)
unpack_debs() { # unpack_debs FOLDER_OF_DEBS DEST
    local deb ok=0
    mkdir -p "$2"
    for deb in "$1"/*.deb; do
        [[ -e $deb ]] || continue
        dpkg -x "$deb" "$2" || return 1
        ok=1
    done
    ((ok))
}
have_loader() {
    local ldc d path=${LD_LIBRARY_PATH:-}
    ldc=$(command -v ldconfig || echo /sbin/ldconfig)
    # Not `| grep -q`: under pipefail, ldconfig killed by the early close reads as absent.
    [[ $("$ldc" -p 2>/dev/null) == *"libvulkan.so.1 "* ]] && return 0
    for d in ${path//:/ }; do [[ -e $d/libvulkan.so.1 ]] && return 0; done
    return 1
}
# The Vulkan loader: what the machine has, else the carried packages (into / as root, as
# the device machine's notes do; elsewhere into scratch on LD_LIBRARY_PATH).
if have_loader; then
    PRE_NOTES+=("Vulkan loader: the machine's")
elif [[ -d $PACK/debs/loader ]] && command -v dpkg >/dev/null; then
    if [[ $(id -u) == 0 ]]; then
        for deb in "$PACK"/debs/loader/*.deb; do dpkg -x "$deb" / || PRE_NOTES+=("could not unpack $deb"); done
        "$(command -v ldconfig || echo /sbin/ldconfig)" || true
        PRE_NOTES+=("Vulkan loader: carried packages unpacked into /")
    elif unpack_debs "$PACK/debs/loader" "$WORK/vk/loader"; then
        export LD_LIBRARY_PATH="$WORK/vk/loader/usr/lib/x86_64-linux-gnu${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
        PRE_NOTES+=("Vulkan loader: carried packages in $WORK/vk/loader")
    fi
    have_loader || PRE_NOTES+=("no Vulkan loader found after unpacking the carried packages")
else
    PRE_NOTES+=("no Vulkan loader and no carried packages ($PACK/debs/loader)")
fi
# The driver: where no manifest is installed, NVIDIA's from its mounted driver folder.
icd_found=0
for d in /etc/vulkan/icd.d /usr/share/vulkan/icd.d /usr/local/share/vulkan/icd.d; do
    compgen -G "$d/*.json" >/dev/null && icd_found=1
done
if [[ -z ${VK_DRIVER_FILES:-}${VK_ICD_FILENAMES:-} ]] && ((!icd_found)); then
    nvidia_icd=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
    if [[ -f $nvidia_icd ]]; then
        export VK_DRIVER_FILES=$nvidia_icd VK_ICD_FILENAMES=$nvidia_icd
        PRE_NOTES+=("driver: VK_DRIVER_FILES=$nvidia_icd")
    else
        PRE_NOTES+=("no Vulkan driver manifest found")
    fi
fi
# The validation layer: the machine's, else the carried package, unpacked into scratch
# (never into /) with its manifest pointed at the library by absolute path.
layer_found=0
layer_path=${VK_LAYER_PATH:-}:${VK_ADD_LAYER_PATH:-}
for d in ${layer_path//:/ } /etc/vulkan/explicit_layer.d /usr/share/vulkan/explicit_layer.d \
    /usr/local/share/vulkan/explicit_layer.d; do
    [[ -f $d/VkLayer_khronos_validation.json ]] && layer_found=1
done
if ((layer_found)) && [[ ${GPU_CHECK_CARRIED_LAYERS:-0} != 1 ]]; then
    PRE_NOTES+=("validation layer: the machine's")
elif [[ -d $PACK/debs/layers ]] && command -v dpkg >/dev/null && unpack_debs "$PACK/debs/layers" "$WORK/vk/layers"; then
    manifest=$(find "$WORK/vk/layers" -name VkLayer_khronos_validation.json | head -n1)
    library=$(find "$WORK/vk/layers" -name libVkLayer_khronos_validation.so | head -n1)
    if [[ -n $manifest && -n $library ]]; then
        mkdir -p "$WORK/vk/layer.d"
        sed -E "s|\"library_path\"[[:space:]]*:[[:space:]]*\"[^\"]*\"|\"library_path\": \"$library\"|" \
            "$manifest" >"$WORK/vk/layer.d/VkLayer_khronos_validation.json"
        export VK_LAYER_PATH="$WORK/vk/layer.d" VK_ADD_LAYER_PATH="$WORK/vk/layer.d"
        PRE_NOTES+=("validation layer: carried package, VK_LAYER_PATH=$WORK/vk/layer.d")
    else
        PRE_NOTES+=("the carried validation-layer package holds no manifest or library")
    fi
else
    PRE_NOTES+=("no validation layer installed and none carried ($PACK/debs/layers): step 2 will fail")
fi
# vulkaninfo, for the driver's version: the machine's or the carried one (scratch only).
VULKANINFO=()
if command -v vulkaninfo >/dev/null; then
    VULKANINFO=(vulkaninfo)
elif [[ -d $PACK/debs/tools ]] && command -v dpkg >/dev/null && unpack_debs "$PACK/debs/tools" "$WORK/vk/tools" &&
    [[ -x $WORK/vk/tools/usr/bin/vulkaninfo ]]; then
    VULKANINFO=(env "LD_LIBRARY_PATH=$WORK/vk/tools/usr/lib/x86_64-linux-gnu${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
        "$WORK/vk/tools/usr/bin/vulkaninfo")
fi
# The binaries: GPU_CHECK_BIN, the packed folder (plain or compressed), else target/release.
BIN_SOURCE=""
find_bins() {
    local dir
    if [[ -n ${GPU_CHECK_BIN:-} ]]; then
        dir=$GPU_CHECK_BIN
    elif [[ -d $PACK/bin ]]; then
        dir=$PACK/bin
    elif compgen -G "$PACK/bin.tar*" >/dev/null; then
        mkdir -p "$WORK/bin" && tar -xf "$(compgen -G "$PACK/bin.tar*" | head -n1)" -C "$WORK/bin" || return 1
        dir=$WORK/bin
    else
        FLY=target/release/flythrough CS=target/release/citystream
        BIND=$(find target/release/deps -maxdepth 1 -type f -name 'bind_cost-*' ! -name '*.*' -perm -u+x \
            -printf '%T@ %p\n' 2>/dev/null | sort -rn | head -n1 | cut -d' ' -f2-)
        BIN_SOURCE=target/release
        return 0
    fi
    FLY=$dir/flythrough CS=$dir/citystream BIND=$dir/bind_cost BIN_SOURCE=$dir
}
FLY="" CS="" BIND=""
find_bins || PRE_NOTES+=("could not unpack the packed binaries")
BINS_OK=1
for b in "$FLY" "$CS" "$BIND"; do
    if [[ -z $b || ! -x $b ]]; then
        PRE_NOTES+=("missing binary ${b:-bind_cost} (build: make gpu-check-pack, or cargo build --release and cargo bench --no-run)")
        BINS_OK=0
    fi
done
if ((BINS_OK)); then
    FLY=$(cd "$(dirname "$FLY")" && pwd)/$(basename "$FLY")
    CS=$(cd "$(dirname "$CS")" && pwd)/$(basename "$CS")
    BIND=$(cd "$(dirname "$BIND")" && pwd)/$(basename "$BIND")
    if ! version=$("$FLY" --version 2>&1); then
        PRE_NOTES+=("$FLY does not run here: $(printf '%s' "$version" | head -n3)")
        BINS_OK=0
    else
        PRE_NOTES+=("binaries from $BIN_SOURCE ($version)")
    fi
fi
[[ -f $PACK/PACK_INFO ]] && PRE_NOTES+=("pack: $(tr '\n' ' ' <"$PACK/PACK_INFO")")
{
    printf '%s\n' "${PRE_NOTES[@]}"
    env | grep -E '^(VK_|LD_LIBRARY_PATH=|CITYSTREAM_)' | sort
} >"$WORK/logs/0-preflight.log"
for n in "${PRE_NOTES[@]}"; do say "preflight: $n"; done
PRE_SECS=$(awk -v a="$PRE_T0" -v b="$(now)" 'BEGIN { printf "%.1f", b - a }')
if ((BINS_OK)); then
    record 0 0 preflight "binaries, Vulkan loader, driver, validation layer" ok 0 "$PRE_SECS" "" "" "" \
        "$(IFS=';'; printf '%s' "${PRE_NOTES[*]}")"
else
    record 0 0 preflight "binaries, Vulkan loader, driver, validation layer" failed 1 "$PRE_SECS" "" "" "" \
        "$(IFS=';'; printf '%s' "${PRE_NOTES[*]}")"
fi

# --- 1: device and sparse shapes ----------------------------------------------------------
if ! ((BINS_OK)); then
    say "no binaries: every step is skipped"
elif wants_step 1; then
    if command -v nvidia-smi >/dev/null; then
        timeout 30 nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader \
            >"$WORK/logs/1-nvidia-smi.txt" 2>&1 || true
    fi
    if ((${#VULKANINFO[@]})); then
        timeout 30 "${VULKANINFO[@]}" --summary >"$WORK/logs/1-vulkaninfo.txt" 2>&1 || true
    fi
    dir=$WORK/runs/1-bind-cost
    mkdir -p "$dir"
    run_step 1 1 device "device, driver, Vulkan version; sparse block shapes and tails; bind_cost" \
        "$(est 40 0 90 0)" "$dir" "" -- env "CITYSTREAM_BENCH_OUT=$dir/bind_cost.csv" "$BIND"
    [[ -f $dir/bind_cost.csv ]] && cp "$dir/bind_cost.csv" "$OUT_DIR/bind_cost.csv"
    device_line=$(grep -m1 '^device:' "$WORK/logs/1.log" 2>/dev/null || true)
    [[ -n $device_line ]] && say "$device_line"
    grep -E 'x4 layers:' "$WORK/logs/1.log" 2>/dev/null | while IFS= read -r line; do say "  $line"; done
    if [[ ${device_line,,} == *llvmpipe* || ${device_line,,} == *lavapipe* || ${device_line,,} == *softpipe* ]]; then
        DEVICE_CLASS=cpu
        say "a CPU device: estimates from here on are lavapipe's"
    fi
else
    skip_step 1 1 device "device, driver, Vulkan version; sparse block shapes and tails; bind_cost" "not in GPU_CHECK_STEPS"
fi

# is_dataset DIR: whether DIR holds a dataset citystream opens.
is_dataset() { [[ -d $1 ]] && "$CS" info "$1" >/dev/null 2>&1; }

# --- 2: the default city, sparse, under validation --------------------------------------------
CITY_DIR=$DATA/city
if ((BINS_OK)) && wants_step 2; then
    city_ready=0
    if is_dataset "$CITY_DIR"; then
        city_ready=1
        record 2a 2 dataset "the default city ($CITY_DIR)" ok 0 0 "" "" "" "already there"
    else
        # What the flythrough's first run does (tools/gen/src/default_city.rs), as two commands.
        # shellcheck disable=SC2016 # the arguments expand in the inner shell
        run_step 2a 2 dataset "create the default city ($CITY_DIR)" "$(est 40 0 120 0)" "" "" -- \
            bash -c '"$1" gen --preset small --seed 1 --out "$2-per-mesh" --quiet &&
                     "$1" atlas "$2-per-mesh" --atlas-extent 2048 --packing regions --out "$2" --quiet' \
            _ "$CS" "$CITY_DIR" && city_ready=1
    fi
    dir=$WORK/runs/2-sparse-validation
    title="default city, standard path, --sparse on, validation (sync) and bind checks"
    if ((city_ready)); then
        mkdir -p "$dir"
        bind_env=()
        [[ $BIND_LOG == 1 ]] && bind_env=("CITYSTREAM_BIND_LOG=$dir/bind.log")
        run_step 2 2 validation "$title" "$(est 30 1.5 90 15 "${PATH_S:-60}")" "$dir" \
            "dataset=$CITY_DIR;sparse=on;clock=fixed;bind_latency=desktop;duration_s=${PATH_S:-path}" -- \
            env CITYSTREAM_VALIDATION=sync CITYSTREAM_VULKAN_WARNINGS=1 CITYSTREAM_CHECK_BINDS=1 "${bind_env[@]}" \
            "$FLY" --dataset "$CITY_DIR" --path standard --sparse on --validation true --clock fixed \
            --bind-latency desktop --frame-interval 900 --out "$dir" ${PATH_S:+--duration-s "$PATH_S"}
        state2=$LAST_STATE
        # Validation messages by severity and id, most frequent first.
        if [[ -f $WORK/logs/2.log ]]; then
            grep -E '^\[vulkan (validation error|warning)\] ' "$WORK/logs/2.log" |
                sed -E 's/^\[vulkan (validation error|warning)\] ([^:]*):.*/\1\t\2/' |
                sort | uniq -c | sort -rn | sed -E 's/^ *([0-9]+) /\1\t/' \
                >"$dir/validation-messages.tsv"
            errors=$(grep -c '^\[vulkan validation error\] ' "$WORK/logs/2.log")
            warnings=$(grep -c '^\[vulkan warning\] ' "$WORK/logs/2.log")
            say "     2: ${errors} validation error(s), ${warnings} warning(s) printed"
        fi
        if [[ -f $dir/bind.log ]]; then
            # Kept, compressed, only to replay a failure (citystream bind-replay).
            if [[ $state2 != ok ]] && [[ $(stat -c %s "$dir/bind.log") -lt $((200 << 20)) ]]; then
                gzip -f "$dir/bind.log"
                [[ $(stat -c %s "$dir/bind.log.gz") -gt $((8 << 20)) ]] && rm -f "$dir/bind.log.gz"
            fi
            rm -f "$dir/bind.log"
        fi
    else
        skip_step 2 2 validation "$title" "no default city"
    fi
elif ((BINS_OK)); then
    skip_step 2 2 validation "default city, standard path, --sparse on, validation" "not in GPU_CHECK_STEPS"
fi

# ensure_gen ID STEP PRESET DIR ESTIMATE: the generated city DIR, reused when there.
ensure_gen() {
    local id=$1 step=$2 preset=$3 dir=$4 estimate=$5
    if is_dataset "$dir"; then
        record "$id" "$step" dataset "the $preset city ($dir)" ok 0 0 "" "" "" "already there"
        return 0
    fi
    run_step "$id" "$step" dataset "citystream gen --preset $preset ($dir)" "$estimate" "" "" -- \
        "$CS" gen --preset "$preset" --seed 1 --out "$dir"
}

# pass_runs STEP NAME DIR: the four pass-timing runs of a dataset (step 3).
pass_runs() {
    local step=$1 name=$2 data=$3 size w h culling id dir estimate
    for size in 1920x1080 3840x2160; do
        w=${size%x*} h=${size#*x}
        for culling in on off; do
            id=3-$name-$size-culling-$culling
            dir=$WORK/runs/$id
            if [[ $size == 1920x1080 ]]; then
                estimate=$(est 20 2 30 20 "$BENCH_S")
            else
                estimate=$(est 20 3 30 60 "$BENCH_S")
            fi
            [[ $name == city-preset ]] && estimate=$((estimate + 30))
            mkdir -p "$dir"
            run_step "$id" "$step" passes "$name ${w}x${h}, culling $culling" "$estimate" "$dir" \
                "dataset=$data;width=$w;height=$h;culling=$culling;clock=fixed;duration_s=$BENCH_S" -- \
                "$FLY" --dataset "$data" --path standard --width "$w" --height "$h" --culling "$culling" \
                --sparse on --clock fixed --bind-latency none --duration-s "$BENCH_S" --frame-interval 0 \
                --psnr-interval 0 --validation false --out "$dir"
        done
    done
}

# --- 3: the large city's passes -----------------------------------------------------------
LARGE_DIR=$DATA/large
if ((BINS_OK)) && wants_step 3; then
    if ensure_gen 3a 3 large "$LARGE_DIR" "$(est 90 0 300 0)"; then
        pass_runs 3 large "$LARGE_DIR"
    else
        skip_step 3-large 3 passes "large: passes at 1920x1080 and 3840x2160" "no large city"
    fi
elif ((BINS_OK)); then
    skip_step 3 3 passes "large and city preset: passes" "not in GPU_CHECK_STEPS"
fi

# --- 4: real clock, baseline against adaptive, under eviction ------------------------------------
if ((BINS_OK)) && wants_step 4; then
    if is_dataset "$LARGE_DIR"; then
        latency_data=$LARGE_DIR budget=${EVICT_MB:-256}
    elif is_dataset "$CITY_DIR"; then
        latency_data=$CITY_DIR budget=${EVICT_MB:-32}
    else
        latency_data=""
    fi
    if [[ -z $latency_data ]]; then
        skip_step 4 4 latency "real clock, baseline against adaptive" "neither the large city nor the default city is there"
    else
        report_args=()
        # name policy: the flythrough's --policy (headroom is adaptive --controller headroom).
        for run in baseline:baseline adaptive-paper:adaptive adaptive-headroom:headroom; do
            name=${run%%:*} policy=${run#*:}
            id=4-$name
            dir=$WORK/runs/$id
            mkdir -p "$dir"
            run_step "$id" 4 latency "real clock 3840x2160, $name, budget $budget MB" \
                "$(est 25 1.2 120 2 "$REAL_S")" "$dir" \
                "dataset=$latency_data;policy=$policy;budget_mb=$budget;clock=real;duration_s=$REAL_S" -- \
                "$FLY" --dataset "$latency_data" --path standard --width 3840 --height 2160 --policy "$policy" \
                --memory-budget-mb "$budget" --sparse on --clock real --duration-s "$REAL_S" \
                --frame-interval 0 --validation false --out "$dir"
            [[ -f $dir/summary.json ]] && report_args+=(--run "$dir" --name "$name")
        done
        if ((${#report_args[@]})); then
            dir=$WORK/runs/4-report
            run_step 4-report 4 report "citystream report over step 4's runs" "$(est 15 0 30 0)" "$dir" "" -- \
                "$CS" report "${report_args[@]}" --out "$dir"
        fi
    fi
elif ((BINS_OK)); then
    skip_step 4 4 latency "real clock, baseline against adaptive" "not in GPU_CHECK_STEPS"
fi

# --- 5: bind_cost again ---------------------------------------------------------------------------
if ((BINS_OK)) && wants_step 5; then
    dir=$WORK/runs/5-bind-cost
    mkdir -p "$dir"
    run_step 5 5 bind "bind_cost bench (again, after the flights)" "$(est 40 0 90 0)" "$dir" "" -- \
        env "CITYSTREAM_BENCH_OUT=$dir/bind_cost.csv" "$BIND"
elif ((BINS_OK)); then
    skip_step 5 5 bind "bind_cost bench" "not in GPU_CHECK_STEPS"
fi

# --- 3, continued: the city preset, last, when time allows ------------------------------------------------
PRESET_DIR=$DATA/city-preset
if ((BINS_OK)) && wants_step 3 && [[ $CITY_PRESET != 0 ]]; then
    gen_estimate=$(est 240 0 2400 0)
    runs_estimate=$((4 * $(est 50 3 60 60 "$BENCH_S")))
    if [[ $CITY_PRESET == auto ]] && ! is_dataset "$PRESET_DIR" && ! fits $((gen_estimate + runs_estimate)); then
        skip_step 3c 3 dataset "the city preset (gen and four runs)" \
            "estimated $((gen_estimate + runs_estimate)) s, $(remaining_s) s left"
    elif ensure_gen 3c 3 city "$PRESET_DIR" "$gen_estimate"; then
        pass_runs 3 city-preset "$PRESET_DIR"
    fi
fi

# --- summary --------------------------------------------------------------------------------------
say "writing the summary"
SPENT=$(elapsed)
if command -v "$PYTHON" >/dev/null && "$PYTHON" "$ROOT/tools/scripts/gpu-check-summary.py" --work "$WORK" --out "$OUT_DIR" \
    --budget "$BUDGET_S" --spent "$SPENT" --pack "$PACK" 2>>"$LOG"; then
    :
else
    # No Python (or it failed): the step table and the binaries' own lines; the raw
    # summary.json files are in the tarball.
    say "python3 missing or failed: a plain summary; every summary.json is in gpu-check-runs.tar.gz"
    json_str() { # a JSON string; "-" (none) is null
        [[ $1 == - ]] && { printf 'null'; return; }
        printf '"%s"' "$(printf '%s' "$1" | sed -e 's/\\/\\\\/g' -e 's/"/\\"/g')"
    }
    json_num() { if [[ $1 =~ ^[0-9]+([.][0-9]+)?$ ]]; then printf '%s' "$1"; else printf 'null'; fi; }
    {
        printf '{\n  "budget_s": %s,\n  "spent_s": %s,\n  "summarised_by": "gpu-check.sh without python3",\n  "steps": [' \
            "$BUDGET_S" "$SPENT"
        first=1
        while IFS=$'\t' read -r id step kind title state rc secs estimate run_dir params note; do
            [[ $id == id ]] && continue
            ((first)) || printf ','
            first=0
            printf '\n    {"id": %s, "step": %s, "kind": %s, "title": %s, "state": %s, "exit_status": %s, "seconds": %s, "estimate_s": %s, "params": %s, "note": %s}' \
                "$(json_str "$id")" "$(json_str "$step")" "$(json_str "$kind")" "$(json_str "$title")" \
                "$(json_str "$state")" "$(json_num "$rc")" "$(json_num "$secs")" "$(json_num "$estimate")" "$(json_str "$params")" \
                "$(json_str "$note")"
        done <"$WORK/steps.tsv"
        printf '\n  ]\n}\n'
    } >"$OUT_DIR/gpu-check.json"
    {
        printf '# GPU check\n\nBudget %s s, spent %s s. Summarised without python3: the figures are in each run'"'"'s summary.json, in gpu-check-runs.tar.gz.\n\n' \
            "$BUDGET_S" "$SPENT"
        printf '| id | step | state | exit | s | estimate s | note |\n|---|---|---|---:|---:|---:|---|\n'
        while IFS=$'\t' read -r id step kind title state rc secs estimate run_dir params note; do
            [[ $id == id ]] && continue
            printf '| %s | %s | %s | %s | %s | %s | %s |\n' "$id" "$title" "$state" "$rc" "$secs" "$estimate" \
                "$(printf '%s' "$note" | sed 's/|/\\|/g')"
        done <"$WORK/steps.tsv"
        if [[ -f $WORK/logs/1.log ]]; then
            printf '\n## Device and sparse shapes (bind_cost)\n\n```\n'
            cat "$WORK/logs/1-nvidia-smi.txt" 2>/dev/null
            grep -E '^(device:|sparseAddressSpaceSize|image:)|x4 layers:' "$WORK/logs/1.log"
            printf '```\n'
        fi
        if [[ -s $WORK/runs/2-sparse-validation/validation-messages.tsv ]]; then
            printf '\n## Step 2 validation messages (count, severity, id)\n\n```\n'
            head -n 40 "$WORK/runs/2-sparse-validation/validation-messages.tsv"
            printf '```\n'
        fi
        while IFS=$'\t' read -r id step kind title state rest; do
            [[ $state == failed || $state == timed-out ]] || continue
            printf '\n## %s failed (%s): the end of its log\n\n```\n' "$id" "$state"
            tail -n 12 "$WORK/logs/$id.log" 2>/dev/null | cut -c1-300
            printf '```\n'
        done <"$WORK/steps.tsv"
        if [[ -f $WORK/runs/4-report/table.md ]]; then
            printf '\n## Step 4: citystream report\n\n'
            cat "$WORK/runs/4-report/table.md"
        fi
    } >"$OUT_DIR/gpu-check.md"
fi

# Every step's log and outputs, compressed; without PNGs and CSVs if that is too large.
tarball=$OUT_DIR/gpu-check-runs.tar.gz
tar -czf "$tarball" -C "$WORK" steps.tsv logs runs 2>>"$LOG"
if [[ $(stat -c %s "$tarball" 2>/dev/null || echo 0) -gt $((15 << 20)) ]]; then
    say "the tarball is over 15 MiB: leaving out PNGs, frames.csv and bind logs"
    tar -czf "$tarball" -C "$WORK" --exclude='*.png' --exclude='frames.csv' --exclude='bind.log*' \
        steps.tsv logs runs 2>>"$LOG"
fi

say "done in $(elapsed) s of ${BUDGET_S} s: $OUT_DIR/gpu-check.md"
cat "$OUT_DIR/gpu-check.md"
if ((FAILED)); then
    say "a step failed (see the table above)"
    exit 1
fi
exit 0
