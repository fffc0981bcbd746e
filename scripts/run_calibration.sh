#!/usr/bin/env bash
# One calibration run as a ROS 2 node graph: simulator, detector, estimator, selector and MCAP
# recorder as separate processes, each with its parameter file from calibration_bringup/config.
# Run with --help for the options. Uses `ros2 run` when a `ros2` command exists (a full ROS 2
# install with the workspace sourced); otherwise the same installed executables (this repo's
# .venv after `make setup`, or any prefix on AMENT_PREFIX_PATH).
set -euo pipefail

usage() {
  cat <<'EOF'
Usage: scripts/run_calibration.sh [options]

Runs one online calibration of a simulated arm (the iCub right arm by default) and records it to MCAP.

  --robot R         robot description: a packaged name (icub_right_arm, ur5e) or a YAML path,
                    passed to every node's robot parameter             (default: icub_right_arm)
  --strategy S      random | al | ucsal | ccsal                         (default: al)
  --iterations N    measurement attempts (selector iterations)          (default: 50)
  --seed S          seed of the real robot, the initial guess and the selector (default: 1)
  --output DIR      where the bag, logs, model and report go; new or empty (default: results/run)
  --overwrite       reuse a non-empty DIR: the previous run's outputs are removed first
  --resume DIR      continue the interrupted run in DIR with its settings, the estimator's checkpoint
                    and the selector's record; the new part of the bag goes to DIR/run.<k>.mcap
  --noise M         pose_dependent | constant (the paper's CN baseline) (default: pose_dependent)
  --estimator E     map (online MAP smoother) | ekf (the paper's filter) (default: map)
  --body-change SPEC  change the real robot mid-run, e.g. 'r_wrist_prosup.d+0.010 r_shoulder_yaw.offset+3'
                    (joint.a|d [m] or joint.alpha|offset [deg], signed increments)
  --body-change-at N  the iteration at whose command the body changes (default: half the iterations)
  --camera-error 'M DEG'  the real camera is M metres and DEG degrees off its description's pose (seeded),
                    and the estimator estimates its pose with that prior one-sigma (default: known)
  --marker-error 'M DEG'  the same for the marker's offset on the flange (default: known)
  --rtf F           simulated seconds per wall second; 0 = as fast as possible (default: 1.0)
  --image-size WxH  camera resolution, intrinsics scale with it         (default: the description's camera)
  --image-encoding E  what the simulated camera publishes: rgb8, bgr8, mono8, mono16, rgba8, bayer_rggb8,
                    bayer_bggr16, yuv422, yuv422_yuy2, ... (any sensor_msgs camera encoding) (default: rgb8)
  --demosaicing M   the detector's demosaicing of a Bayer camera: vng | edge_aware | bilinear | mosaic
                    (mosaic: every photosite read as grey, for a white-balanced sensor)  (default: vng)
  --transport T     raw | compressed: the detector reads image_raw (sensor_msgs/Image) or image_transport's
                    image_raw/compressed (JPEG, quality 90); the bag records that stream  (default: raw)
  --camera-info FILE  the detector's intrinsics from a camera_info_manager YAML (ost.yaml, as the ROS
                    camera_calibration tool writes it) instead of the camera_info topic
  --eyes E          left | both: a robot with eyes detects with the left eye, or with both fused and the
                    selection planned for either (default: both; left with --camera-error or --marker-error,
                    whose corrections are one camera's; a fixed camera has its one)
  --no-images       do not record the camera images (smaller bag)
  --domain-id N     ROS_DOMAIN_ID 0-232; refused if another run holds it or a graph talks on it
                    (default: a free one in 100-199; discovery is localhost-only)
  --timeout SEC     give up after this many wall seconds (default: 60 + 20 per iteration)
  --max-timeouts F  fail a run whose iterations ended 'timeout' in more than this fraction (default: 0.2)
  --max-dh-difference D  fail a run whose offline re-run ends with a DH table more than D (m or rad)
                    away from the online estimate's in any parameter (default: 1e-4)
  --viz             serve the live 3D view (calibration_viz) and print its URL
  --viz-port N      its port (default: 8080)
  --plan-only       plan --iterations poses from the initial guess without starting any node or moving
                    anything, write them to DIR/plan.yaml for review (with --viz: show them and the
                    obstacles in the browser until Ctrl-C)
  --poses FILE      visit the poses of FILE (a reviewed plan or a hand-taught pose list) first, each
                    checked against the collision margins, before the strategy takes over
  --speed-scale F   command the joints at F (0-1] times their speed limit (default: 1.0)
  --margin M        collision margin [m] to the obstacles (default: the description's collision.margin)
  --no-collision-check  do not check targets and paths against the obstacles (simulation only: to measure
                    what the check costs; the simulator still counts the contacts)
  -h, --help        this text

Before anything starts, the robot description (and a --poses file) is validated with the loader
every node uses: a bad one exits 2 with one line naming the file and the field.

Writes DIR/calibration.mcap, DIR/report.md (+ PNG plots, metrics.csv), DIR/model/ (calibrated
DH YAML and URDF), DIR/progress.jsonl, DIR/checkpoint.npz, DIR/run.env (settings, run id, domain)
and DIR/logs/<node>.log. Exit status 0 on a finished, healthy run; 1 if a node dies (with its log
tail), the run times out, a node had to be killed, or the health check fails (too many timeouts,
offline re-run disagreeing with the online estimate); 2 on a bad option; 130 on Ctrl-C. Every
node started is stopped on every exit path (SIGINT, then SIGKILL of its process group).
EOF
}

die() { echo "run_calibration: $*" >&2; exit 2; }
need_value() {  # need_value FLAG ARGS...: the flag's value is the next word, not another flag
  [ $# -ge 2 ] && [[ "$2" != --* ]] || die "$1 needs a value (see --help)"
}
is_number() { [[ "$1" =~ ^[0-9]*\.?[0-9]+$ ]]; }

robot=icub_right_arm; strategy=al; iterations=50; seed=1; output=results/run; noise=pose_dependent; rtf=1.0; estimator=map
body_change=""; body_change_at=""; camera_error=""; marker_error=""; overwrite=0; resume=""
image_size=""; image_encoding=rgb8; demosaicing=""; transport=raw; camera_info=""; eyes=""; record_images=1; domain_id=""; timeout=""; viz=0; viz_port=8080
max_timeouts=0.2; max_dh_difference=1e-4
plan_only=0; poses=""; speed_scale=1.0; margin=""; collision_check=1
given=()   # run-defining options on the command line (a resumed run keeps its own)
while [ $# -gt 0 ]; do
  case "$1" in
    --robot|--strategy|--iterations|--seed|--noise|--estimator|--body-change|--body-change-at|--image-size|\
    --camera-error|--marker-error|--poses|--speed-scale|--margin|--image-encoding|--demosaicing|--transport|--camera-info|--rtf|\
    --eyes)
      need_value "$@"; given+=("$1") ;;&
    --output|--resume|--domain-id|--timeout|--viz-port|--max-timeouts|--max-dh-difference)
      need_value "$@" ;;&
    --robot) robot=$2; shift 2 ;;
    --strategy) strategy=$2; shift 2 ;;
    --iterations) iterations=$2; shift 2 ;;
    --seed) seed=$2; shift 2 ;;
    --output) output=$2; shift 2 ;;
    --overwrite) overwrite=1; shift ;;
    --resume) resume=$2; shift 2 ;;
    --noise) noise=$2; shift 2 ;;
    --estimator) estimator=$2; shift 2 ;;
    --body-change) body_change=$2; shift 2 ;;
    --body-change-at) body_change_at=$2; shift 2 ;;
    --rtf) rtf=$2; shift 2 ;;
    --camera-error) camera_error=$2; shift 2 ;;
    --marker-error) marker_error=$2; shift 2 ;;
    --image-size) image_size=$2; shift 2 ;;
    --image-encoding) image_encoding=$2; shift 2 ;;
    --demosaicing) demosaicing=$2; shift 2 ;;
    --transport) transport=$2; shift 2 ;;
    --camera-info) camera_info=$2; shift 2 ;;
    --eyes) eyes=$2; shift 2 ;;
    --no-images) record_images=0; given+=("$1"); shift ;;
    --no-collision-check) collision_check=0; given+=("$1"); shift ;;
    --domain-id) domain_id=$2; shift 2 ;;
    --timeout) timeout=$2; shift 2 ;;
    --max-timeouts) max_timeouts=$2; shift 2 ;;
    --max-dh-difference) max_dh_difference=$2; shift 2 ;;
    --viz) viz=1; shift ;;
    --viz-port) viz_port=$2; shift 2 ;;
    --plan-only) plan_only=1; shift ;;
    --poses) poses=$2; shift 2 ;;
    --speed-scale) speed_scale=$2; shift 2 ;;
    --margin) margin=$2; shift 2 ;;
    -h|--help) usage; exit 0 ;;
    *) die "unknown option '$1' (see --help)" ;;
  esac
done

if [ -n "$resume" ]; then
  # A resumed run is the same run: its settings come from its run.env, not from this command line.
  [ "${#given[@]}" -eq 0 ] || die "--resume continues a run with its own settings; drop ${given[*]}"
  [ "$overwrite" = 0 ] || die "--resume and --overwrite exclude each other"
  [ -f "$resume/run.env" ] || die "--resume: '$resume' holds no run.env (not a run_calibration output directory)"
  # shellcheck disable=SC1091  # written by this script with printf %q
  source "$resume/run.env"
  output=$resume
fi
case "$strategy" in random|al|ucsal|ccsal) ;; *) die "--strategy must be random, al, ucsal or ccsal, got '$strategy'" ;; esac
case "$noise" in pose_dependent|constant) ;; *) die "--noise must be pose_dependent or constant, got '$noise'" ;; esac
case "$estimator" in map|ekf) ;; *) die "--estimator must be map or ekf, got '$estimator'" ;; esac
case "$transport" in raw|compressed) ;; *) die "--transport must be raw or compressed, got '$transport'" ;; esac
case "$eyes" in ''|left|both) ;; *) die "--eyes must be left or both, got '$eyes'" ;; esac
if [ -n "$camera_error$marker_error" ]; then
  # The extrinsic corrections the estimator estimates are one camera's (the left eye's).
  [ "$eyes" != both ] || die "--eyes both and --camera-error / --marker-error exclude each other"
  eyes=left
fi
if [ -n "$camera_info" ]; then
  [ -f "$camera_info" ] || die "--camera-info: no file '$camera_info'"
  camera_info=$(cd "$(dirname "$camera_info")" && pwd)/$(basename "$camera_info")   # the nodes run elsewhere
fi
[[ "$iterations" =~ ^[1-9][0-9]*$ ]] || die "--iterations must be a positive integer, got '$iterations'"
[[ "$seed" =~ ^[0-9]+$ ]] || die "--seed must be a non-negative integer, got '$seed'"
[[ -n "$robot" ]] || die "--robot must name a robot description"
size_args=(); size_text="the description's image size"
if [ -n "$image_size" ]; then
  [[ "$image_size" =~ ^([1-9][0-9]*)x([1-9][0-9]*)$ ]] || \
    die "--image-size must look like 640x480 (positive sizes), got '$image_size'"
  size_args=(-p "image_width:=${BASH_REMATCH[1]}" -p "image_height:=${BASH_REMATCH[2]}")
  size_text=$image_size
fi
is_number "$rtf" || die "--rtf must be a non-negative number, got '$rtf'"
[[ "$rtf" == *.* ]] || rtf="$rtf.0"   # a double parameter: '4' would be declared an integer and refused
[[ "$viz_port" =~ ^[0-9]+$ ]] && (( viz_port >= 1 && viz_port <= 65535 )) || die "--viz-port must be a port number, got '$viz_port'"
[ -z "$timeout" ] || [[ "$timeout" =~ ^[1-9][0-9]*$ ]] || die "--timeout must be a positive integer (seconds), got '$timeout'"
timeout=${timeout:-$((60 + 20 * iterations))}
[ -z "$domain_id" ] || { [[ "$domain_id" =~ ^[0-9]+$ ]] && (( domain_id <= 232 )); } || \
  die "--domain-id must be an integer 0-232, got '$domain_id'"
[[ "$max_timeouts" =~ ^(0(\.[0-9]*)?|1(\.0*)?|\.[0-9]+)$ ]] || die "--max-timeouts must be a fraction 0-1, got '$max_timeouts'"
[[ "$max_dh_difference" =~ ^[0-9]*\.?[0-9]+([eE][-+]?[0-9]+)?$ ]] || \
  die "--max-dh-difference must be a non-negative number (m or rad), got '$max_dh_difference'"
[[ "$speed_scale" =~ ^(0?\.[0-9]*[1-9][0-9]*|1(\.0*)?)$ ]] || die "--speed-scale must be a fraction in (0, 1], got '$speed_scale'"
[ -z "$margin" ] || [[ "$margin" =~ ^(0?\.[0-9]+|0|1(\.0*)?)$ ]] || die "--margin must be a distance 0-1 (m), got '$margin'"
[ -z "$poses" ] || [ "$plan_only" = 0 ] || die "--poses and --plan-only exclude each other"
[ -z "$margin" ] || [ "$collision_check" = 1 ] || die "--margin and --no-collision-check exclude each other"
[[ "$speed_scale" == *.* ]] || speed_scale="$speed_scale.0"   # double parameters: '1' would be an integer
[ -z "$margin" ] || [[ "$margin" == *.* ]] || margin="$margin.0"
body_change_at=${body_change_at:-$(( (iterations + 1) / 2 + 1 ))}
if [ -n "$body_change" ]; then
  [[ "$body_change_at" =~ ^[1-9][0-9]*$ ]] || die "--body-change-at must be a positive integer, got '$body_change_at'"
else
  body_change_at=0
fi
# --- The robot description (and a pose list), with the loader every node uses ---------------
repo=$(cd "$(dirname "$0")/.." && pwd)
if ! command -v ros2 >/dev/null 2>&1 && [ -x "$repo/.venv/bin/python" ]; then
  # This repository's venv is the install prefix (see `make setup`).
  export PATH="$repo/.venv/bin:$PATH"
  export AMENT_PREFIX_PATH="$repo/.venv${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
fi
[ -z "$poses" ] || poses=$(cd "$(dirname "$poses")" 2>/dev/null && echo "$PWD/$(basename "$poses")") || \
  die "--poses: '$poses' does not exist"
invalid=$(python3 -m calibration_interfaces.validate --robot "$robot" ${poses:+--poses "$poses"} 2>&1 >/dev/null) || \
  die "$(tail -n 1 <<<"$invalid")"
[ "$eyes" != both ] || python3 -c 'import sys; from body_schema import load_robot
sys.exit(load_robot(sys.argv[1]).eyes is None)' "$robot" 2>/dev/null || \
  die "--eyes both: robot '$robot' has a fixed camera, no eyes"
if [ "$plan_only" = 1 ]; then
  # Nothing starts and nothing moves: the poses a run would visit, from the initial guess, for review.
  mkdir -p "$output"
  plan_args=(--robot "$robot" --n "$iterations" --seed "$seed" --output "$output/plan.yaml")
  [ -z "$strategy" ] || plan_args+=(--strategy "$strategy")
  [ -z "$margin" ] || plan_args+=(--margin "$margin")
  [ "$collision_check" = 1 ] || plan_args+=(--no-collision-check)
  [ -z "$camera_error" ] || plan_args+=(--camera-prior "$camera_error")
  [ -z "$marker_error" ] || plan_args+=(--marker-prior "$marker_error")
  [ "$viz" = 0 ] || plan_args+=(--viz --viz-port "$viz_port")
  exec python3 -m calibration_bringup.plan "${plan_args[@]}"
fi

# The output directory: new or empty, unless the run resumes it or the user asked to overwrite it
# (then only what a run writes is removed, so no stale report or model sits beside the new bag).
if [ -z "$resume" ] && [ -d "$output" ] && [ -n "$(ls -A "$output")" ]; then
  [ "$overwrite" = 1 ] || die "--output '$output' is not empty (--overwrite replaces the previous run, --resume '$output' continues it)"
  (cd "$output" && rm -rf -- calibration.mcap run.*.mcap report.md metrics.csv ./*.png progress.jsonl \
     checkpoint.npz run.env run.ids model logs)
fi

# --- Where the executables and parameter files are ----------------------------------------
share_dir() {   # share/<pkg> of the first prefix on AMENT_PREFIX_PATH that has it
  local prefix
  IFS=: read -ra prefixes <<<"${AMENT_PREFIX_PATH:-}"
  for prefix in "${prefixes[@]}"; do
    if [ -f "$prefix/share/ament_index/resource_index/packages/$1" ]; then echo "$prefix/share/$1"; return 0; fi
  done
  return 1
}
command_of() {  # the command line that runs <pkg> <exe>
  local pkg=$1 exe=$2 prefix
  if command -v ros2 >/dev/null 2>&1; then echo "ros2 run $pkg $exe"; return 0; fi
  IFS=: read -ra prefixes <<<"${AMENT_PREFIX_PATH:-}"
  for prefix in "${prefixes[@]}"; do   # colcon install layout first: <prefix>/lib/<pkg>/<exe>
    if [ -x "$prefix/lib/$pkg/$exe" ]; then echo "$prefix/lib/$pkg/$exe"; return 0; fi
  done
  if command -v "$exe" >/dev/null 2>&1; then command -v "$exe"; return 0; fi
  return 1
}
config=$(share_dir calibration_bringup)/config || \
  die "calibration_bringup is not installed (run 'make setup', or source your colcon workspace)"
# The encoding and the calibration file are checked by the code that will read them, before anything starts.
python3 -c 'import sys; from calibration_interfaces.image_conversion import ENCODINGS as E
sys.exit(0 if sys.argv[1] in E else f"run_calibration: --image-encoding must be one of {sorted(E)}, got {sys.argv[1]!r}")' \
  "$image_encoding" || exit 2
[ -z "$demosaicing" ] || python3 -c 'import sys; from calibration_interfaces.image_conversion import DEMOSAICING as D
sys.exit(0 if sys.argv[1] in D else f"run_calibration: --demosaicing must be one of {list(D)}, got {sys.argv[1]!r}")' \
  "$demosaicing" || exit 2
if [ -n "$camera_info" ]; then
  python3 -c 'import sys; from calibration_interfaces.camera_info_file import CameraInfoFileError, read_camera_info
try:
    read_camera_info(sys.argv[1])
except CameraInfoFileError as exc:
    sys.exit(f"run_calibration: --camera-info: {exc}")' "$camera_info" || exit 2
fi
for pair in icub_sim_bridge:sim_node marker_detector:detector_node dh_estimator:estimator_node \
            active_selector:selector_node calibration_bringup:recorder_node calibration_bringup:calibration_report; do
  command_of "${pair%%:*}" "${pair##*:}" >/dev/null || die "executable ${pair##*:} of ${pair%%:*} not found"
done
if [ "$viz" = 1 ]; then
  command_of calibration_viz viz_node >/dev/null || die "--viz: executable viz_node of calibration_viz not found"
  viz_config=$(share_dir calibration_viz)/config
fi


# --- Every started node is stopped on every exit path ---------------------------------------
declare -A pid=()
order=()
killed=()   # nodes stop had to SIGKILL: their files and exports may be missing
alive() { [ -n "${pid[$1]:-}" ] && kill -0 "${pid[$1]}" 2>/dev/null; }
stop() {    # stop NAME...: SIGINT to each process group (nodes finish files and exports), SIGKILL after 15 s
  local name t any
  for name in "$@"; do alive "$name" && kill -INT -- "-${pid[$name]}" 2>/dev/null || true; done
  for ((t = 0; t < 150; t++)); do    # one deadline for all of them
    any=0
    for name in "$@"; do alive "$name" && { any=1; break; }; done
    (( any )) || break
    sleep 0.1
  done
  for name in "$@"; do
    if alive "$name"; then
      echo "run_calibration: $name did not stop on SIGINT within 15 s; killed" >&2
      kill -KILL -- "-${pid[$name]}" 2>/dev/null || true
      killed+=("$name")
    fi
    [ -z "${pid[$name]:-}" ] || wait "${pid[$name]}" 2>/dev/null || true
  done
}
cleanup() { # the EXIT trap, so also after `set -e`/`set -u` errors: stop what still runs, release the domain
  local rc=$?
  trap '' INT TERM HUP      # a second Ctrl-C must not cut the cleanup short and orphan a node
  [ "${#order[@]}" -eq 0 ] || stop "${order[@]}"
  if (( rc == 0 )) && [ "${#killed[@]}" -gt 0 ]; then
    echo "run_calibration: ${killed[*]} had to be killed; the run's outputs may be incomplete" >&2
    rc=1
  fi
  exit "$rc"
}
trap cleanup EXIT
trap 'echo "run_calibration: interrupted; stopping the graph" >&2; exit 130' INT
trap 'exit 143' TERM
trap 'exit 129' HUP

# --- An isolated graph ----------------------------------------------------------------------
# A domain is held for the whole run by a lock file (the launcher keeps it open), so two
# launchers never pick the same one, and probed for a graph that talks on it already (one not
# started by this script). The run id reaches every node (parameter run_id): a node that sees
# another run's id, or another node of its own name, on its domain stops and the run fails.
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
lock_dir=${TMPDIR:-/tmp}/run_calibration.domains
mkdir -p "$lock_dir"
take_domain() { # take_domain N: lock domain N for this run
  exec {domain_fd}>"$lock_dir/$1.lock"
  flock -n "$domain_fd" || { exec {domain_fd}>&-; return 1; }
}
quiet_domain() { python3 -m calibration_bringup.graph_probe --domain-id "$1" --seconds "$2"; }   # no graph talks on it
if [ -n "$domain_id" ]; then
  take_domain "$domain_id" || die "ROS_DOMAIN_ID $domain_id is used by another run_calibration run; choose another --domain-id or leave it out"
  quiet_domain "$domain_id" 4 || \
    die "ROS_DOMAIN_ID $domain_id already has a ROS graph talking on it (see above); choose another --domain-id or leave it out"
else
  first=$((RANDOM % 100))
  for ((k = 0; k < 100; k++)); do
    candidate=$((100 + (first + k) % 100))
    take_domain "$candidate" || continue
    if quiet_domain "$candidate" 2.5 2>/dev/null; then domain_id=$candidate; break; fi
    echo "run_calibration: ROS_DOMAIN_ID $candidate has a graph not started by this script; trying another" >&2
    exec {domain_fd}>&-
  done
  [ -n "$domain_id" ] || die "no free ROS_DOMAIN_ID in 100-199 (each is held by a run or has a graph talking on it)"
fi
export ROS_DOMAIN_ID=$domain_id
export PYTHONUNBUFFERED=1 RCUTILS_COLORIZED_OUTPUT=0 RCUTILS_LOGGING_BUFFERED_STREAM=0
if [ -z "${FASTRTPS_DEFAULT_PROFILES_FILE:-}" ] && [ -f "$config/fastdds_shm.xml" ]; then
  # Shared-memory segments large enough for whole camera frames (docs/recording.md: Fast DDS).
  export FASTRTPS_DEFAULT_PROFILES_FILE="$config/fastdds_shm.xml"
  export FASTDDS_DEFAULT_PROFILES_FILE="$config/fastdds_shm.xml"
fi
run_id="$(date +%Y%m%dT%H%M%S)-$$-$RANDOM"

mkdir -p "$output/logs"
output=$(cd "$output" && pwd)
resume_args=()
if [ -n "$resume" ]; then
  [ -f "$output/checkpoint.npz" ] || echo "run_calibration: $output has no estimator checkpoint; the estimate starts over" >&2
  for ((k = 1; ; k++)); do [ -e "$output/run.$k.mcap" ] || break; done
  bag="$output/run.$k.mcap"
  mkdir -p "$output/logs/before.run.$k"    # the interrupted part's logs
  for f in "$output"/logs/*.log; do [ -e "$f" ] && mv "$f" "$output/logs/before.run.$k/"; done
  resume_args=(-p "resume:=true")
else
  bag="$output/calibration.mcap"
  {
    for var in robot strategy iterations seed noise estimator body_change body_change_at camera_error marker_error \
               image_size image_encoding demosaicing transport camera_info eyes record_images rtf poses speed_scale margin \
               collision_check; do
      printf '%s=%q\n' "$var" "${!var}"
    done
  } >"$output/run.env"
fi
printf 'run_id=%q\ndomain_id=%q\n' "$run_id" "$domain_id" >"$output/run.ids"   # this part's id and domain

start() {   # start NAME PKG EXE ARGS...: its own process group, so a stop reaches ros2 run's child too
  local name=$1 pkg=$2 exe=$3; shift 3
  # A background job of a script starts with SIGINT ignored; a node still importing (1-4 s on a
  # loaded machine) lost a SIGINT for good that way, so the default disposition is restored first.
  # shellcheck disable=SC2046  # the command line is words on purpose (ros2 run pkg exe)
  ( trap - INT QUIT; exec setsid $(command_of "$pkg" "$exe") "$@" -p "run_id:=$run_id" \
      >"$output/logs/$name.log" 2>&1 ) &
  pid[$name]=$!
  order+=("$name")
}
fail() {    # fail NAME WHY: the node's log tail, then exit 1 (the EXIT trap stops the graph)
  echo "run_calibration: $1 $2; last lines of $output/logs/$1.log:" >&2
  tail -n 25 "$output/logs/$1.log" | sed 's/^/  | /' >&2
  exit 1
}
all_alive() {   # all_alive NAME...: fail the run on the first one that exited
  local name rc
  for name in "$@"; do
    alive "$name" || { wait "${pid[$name]}" && rc=0 || rc=$?; fail "$name" "exited early (status $rc)"; }
  done
}

recorder_args=(-p "output:=$bag" -p "robot:=$robot")
sim_args=()       # rcl refuses an empty value (-p body_change:=), so the change is passed only when asked for
[ -z "$body_change" ] || sim_args=(-p "body_change:=$body_change" -p "body_change_at_command:=$body_change_at")
[ "$record_images" = 1 ] || recorder_args+=(-p "exclude_images:=true")
# The bag records the image stream the detector reads (the other transport is not published, or not wanted).
other_images=$(python3 -c 'import sys; from calibration_interfaces.contract import IMAGE_TOPICS as I, COMPRESSED_IMAGE_TOPICS as C
print("[" + ",".join(t for t in I if (t in C) == (sys.argv[1] == "raw")) + "]")' "$transport")
recorder_args+=(-p "exclude:=$other_images")
sim_args+=(-p "image_encoding:=$image_encoding")
detector_args=(-p "transport:=$transport")
[ -z "$demosaicing" ] || detector_args+=(-p "demosaicing:=$demosaicing")
if [ "$transport" = compressed ]; then sim_args+=(-p "compressed_format:=jpeg"); fi
[ -z "$camera_info" ] || detector_args+=(-p "camera_info_url:=file://$camera_info")
eye_args=()          # the detector fuses and the selector plans for the same eyes
[ -z "$eyes" ] || eye_args=(-p "use_right_eye:=$([ "$eyes" = both ] && echo true || echo false)")
detector_args+=("${eye_args[@]}")
extrinsics_args=()   # the real camera / marker off the description's, estimated with the arm
[ -z "$camera_error" ] || { sim_args+=(-p "camera_perturbation:=$camera_error"); extrinsics_args+=(-p "camera_prior:=$camera_error"); }
[ -z "$marker_error" ] || { sim_args+=(-p "marker_perturbation:=$marker_error"); extrinsics_args+=(-p "marker_prior:=$marker_error"); }
report_args=()       # the report's re-run estimates them too
[ -z "$camera_error" ] || report_args+=(--camera-prior "$camera_error")
[ -z "$marker_error" ] || report_args+=(--marker-prior "$marker_error")

echo "run_calibration: $robot, $strategy, $iterations iterations, seed $seed, noise $noise, estimator $estimator," \
     "$size_text, $image_encoding over $transport, eyes ${eyes:-as the parameter files say}, rtf $rtf," \
     "ROS_DOMAIN_ID $ROS_DOMAIN_ID, run $run_id -> $output"
[ -z "$resume" ] || echo "run_calibration: resuming the run in $output; this part is recorded to $bag"
[ -z "$body_change" ] || echo "run_calibration: the real robot changes by '$body_change' at iteration $body_change_at"
[ -z "$camera_info" ] || echo "run_calibration: the detector's intrinsics come from $camera_info"
wall0=$SECONDS
# The recorder first, so every latched fact (true table, initial estimate, camera poses) is in the bag.
start recorder calibration_bringup recorder_node --ros-args --params-file "$config/recorder.yaml" \
  "${recorder_args[@]}"
for ((t = 0; t < 200; t++)); do [ -s "$bag" ] && break; alive recorder || fail recorder "exited at start"; sleep 0.1; done
[ -s "$bag" ] || fail recorder "did not open $bag within 20 s"
start sim icub_sim_bridge sim_node --ros-args --params-file "$config/sim.yaml" \
  -p "robot:=$robot" -p "perturb_seed:=$seed" -p "real_time_factor:=$rtf" "${size_args[@]}" \
  "${sim_args[@]}"
if [ "$viz" = 1 ]; then   # latched facts (true table, camera poses, estimate) reach it whenever it starts
  start viz calibration_viz viz_node --ros-args --params-file "$viz_config/viz.yaml" -p "port:=$viz_port" \
    -p "robot:=$robot" -p "transport:=$transport"
  echo "run_calibration: live 3D view at http://127.0.0.1:$viz_port (open it in a browser)"
fi
start detector marker_detector detector_node --ros-args --params-file "$config/detector.yaml" -p "robot:=$robot" \
  "${detector_args[@]}"
start estimator dh_estimator estimator_node --ros-args --params-file "$config/estimator.yaml" \
  -p "robot:=$robot" -p "initial_seed:=$seed" -p "noise_model:=$noise" -p "estimator:=$estimator" \
  -p "export_dir:=$output/model" -p "checkpoint_path:=$output/checkpoint.npz" "${extrinsics_args[@]}"
# The selector last, once the recorder records every topic but the selector's own two (/arm/command,
# /calibration/progress): nothing moves and the estimator does not update before the first command,
# so the bag then holds the initial estimate and every observation. (The recorder finds publishers
# by polling the graph; discovering a new process took up to 2 s wall in test runs, and a topic
# subscribed late loses its first messages: a hand pose, or the latched initial estimate replaced
# by the first update.)
recording_all() {
  local want got
  want=$(sed -n 's/.*recording \([0-9]*\) topics to .*/\1/p' "$output/logs/recorder.log" 2>/dev/null | head -n 1)
  got=$(grep -c '\]: recording /' "$output/logs/recorder.log" 2>/dev/null) || true
  [ -n "$want" ] && [ "${got:-0}" -ge $((want - 2)) ]
}
for ((t = 0; t < 200; t++)); do
  recording_all && break
  all_alive "${order[@]}"
  sleep 0.1
done
recording_all || fail recorder "did not subscribe to the other nodes' topics within 20 s"
safety_args=(-p "speed_scale:=$speed_scale")
[ -z "$poses" ] || safety_args+=(-p "poses_file:=$poses")
[ -z "$margin" ] || safety_args+=(-p "collision_margin:=$margin")
[ "$collision_check" = 1 ] || safety_args+=(-p "collision_check:=false")
start selector active_selector selector_node --ros-args --params-file "$config/selector.yaml" \
  -p "robot:=$robot" -p "strategy:=$strategy" -p "iterations:=$iterations" -p "seed:=$seed" -p "noise_model:=$noise" \
  -p "progress_file:=$output/progress.jsonl" -p "wait_for_recorder:=true" "${resume_args[@]}" \
  "${extrinsics_args[@]}" "${safety_args[@]}" "${eye_args[@]}"

# --- Wait for the selector; a node that dies fails the run ----------------------------------
shown=0
echo_iterations() {   # the selector's one log line per iteration, those not shown yet
  local lines
  lines=$(grep ' iteration [0-9]*/' "$output/logs/selector.log" 2>/dev/null | sed 's/^.*\]: /  /') || true
  [ -n "$lines" ] || return 0
  tail -n +$((shown + 1)) <<<"$lines"
  shown=$(wc -l <<<"$lines")
}
while alive selector; do
  all_alive recorder sim detector estimator ${pid[viz]:+viz}
  (( SECONDS - wall0 <= timeout )) || fail selector "did not finish $iterations iterations within $timeout s"
  echo_iterations
  sleep 0.2
done
wait "${pid[selector]}" && rc=0 || rc=$?
echo_iterations
(( rc == 0 )) || fail selector "failed (status $rc)"
wall=$((SECONDS - wall0))

# Estimator before recorder: its export and last messages land first; the recorder then closes the file.
stop selector sim detector estimator ${pid[viz]:+viz}
stop recorder
echo "run_calibration: finished in ${wall} s; writing the report"
calibration_cmd=$(command_of calibration_bringup calibration_report)
# shellcheck disable=SC2086  # the command line is words on purpose (ros2 run pkg exe)
$calibration_cmd --bag "$bag" --output "$output" --wall-seconds "$wall" \
  --title "$robot, $strategy, $iterations iterations, seed $seed, noise $noise, estimator $estimator, $size_text, $image_encoding over $transport" \
  --params-file "$config/estimator.yaml" --noise-model "$noise" --estimator "$estimator" --robot "$robot" "${report_args[@]}"
# The run's health: a run with many timeouts (a stalled estimator) or whose offline re-run
# disagrees with the online estimate is not a result to trust, even if it finished.
python3 -m calibration_bringup.run_check "$output" --max-timeouts "$max_timeouts" \
  --max-dh-difference "$max_dh_difference" ${resume:+--resumed}
