#!/usr/bin/env bash
# Peak resident memory (VmHWM) of a fresh `murk serve` per job kind, for sizing replicas
# (docs/deployment.md#sizing). For each kind: simulate its input, start a new `murk serve` on a
# free loopback port, run the one job against it with the CLI, read the server's VmHWM, stop it.
#
#   cargo build --release -p murk-server
#   deploy/peak-memory.sh [path/to/murk]
#
# Linux only (/proc); needs jq. Takes a few minutes on two cores, most of it simulating the
# inputs.
set -euo pipefail
murk="$(realpath "${1:-target/release/murk}")"
work="$(mktemp -d)"
server=""
trap '[ -n "$server" ] && kill "$server" 2>/dev/null; rm -rf "$work"' EXIT

# Starts `murk serve` and sets $server (its pid) and $url; the address comes from its log.
serve() {
    "$murk" serve --addr 127.0.0.1:0 --log-format json 2>"$work/serve.log" &
    server=$!
    url=""
    for _ in $(seq 1 200); do
        url=$(sed -n 's/.*"message":"murk serving","addr":"\([^"]*\)".*/\1/p' "$work/serve.log" | head -1)
        [ -n "$url" ] && break
        sleep 0.05
    done
    [ -n "$url" ] || { echo "murk serve did not start:" >&2; cat "$work/serve.log" >&2; exit 1; }
    url="http://$url"
}

# Prints "KIND  PEAK MiB" after running the command (with --server appended) on a fresh server.
measure() {
    local kind="$1"
    shift
    serve
    if [ "$#" -gt 0 ]; then
        "$@" --server "$url" >/dev/null 2>"$work/job.log" \
            || { echo "$kind failed:" >&2; cat "$work/job.log" >&2; exit 1; }
    fi
    local kib
    kib=$(awk '/^VmHWM:/ {print $2}' "/proc/$server/status")
    kill "$server"
    wait "$server" 2>/dev/null || true
    server=""
    awk -v kind="$kind" -v kib="$kib" 'BEGIN { printf "%-40s %6.0f MiB\n", kind, kib / 1024 }'
}

"$murk" simulate tof --out "$work/tof" >/dev/null
"$murk" simulate ps --width 128 --height 128 --out "$work/ps128" >/dev/null
"$murk" simulate ps --width 256 --height 256 --out "$work/ps256" >/dev/null
"$murk" simulate mvs --width 640 --height 480 --views 5 --out "$work/mvs" >/dev/null
"$murk" simulate stereo --width 640 --height 480 --frames 1 --out "$work/pair" >/dev/null
pair="$work/pair/$(ls "$work/pair" | head -1)"
ref=$(jq -r .reference "$work/mvs/meta.json")
intrinsics=$(jq -r '.intrinsics | "\(.fx),\(.fy),\(.cx),\(.cy)"' "$pair/meta.json")

echo "peak resident memory of a fresh murk serve, one job ($("$murk" --version))"
measure "idle server"
measure "ToF 512x424" "$murk" tof --frame "$work/tof" --out "$work/out-tof"
measure "photometric stereo 128x128, r = 81" \
    "$murk" ps --capture "$work/ps128" --out "$work/out-ps128" --support-r 81
measure "photometric stereo 256x256, r = 81" \
    "$murk" ps --capture "$work/ps256" --out "$work/out-ps256" --support-r 81
measure "MVS 640x480, 5 views" "$murk" mvs --model "$work/mvs/sparse" --images "$work/mvs/images" \
    --reference "$ref" --out "$work/out-mvs"
measure "rectified stereo 640x480" "$murk" stereo --left "$pair/left.png" --right "$pair/right.png" \
    --intrinsics "$intrinsics" --baseline "$(jq .baseline "$pair/meta.json")" --out "$work/out-stereo"
