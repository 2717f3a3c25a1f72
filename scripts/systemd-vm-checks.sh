#!/bin/bash
# The checks scripts/systemd-vm.sh runs inside its VM (as root, a unit started once the booted
# system is up; the VM powers off when this ends). Results: /vm-test/out/results, one
# PASS/FAIL/INFO line each, END last; logs beside it. Not meant to run on a real machine: it
# installs the package, edits /etc/tagdeflect, adds users and loads the vivid driver.
set -u
export PATH=/usr/sbin:/usr/bin:/sbin:/bin LANG=C.UTF-8 DEBIAN_FRONTEND=noninteractive
. /vm-test/params
O=/vm-test/out
R=$O/results
: >"$R"
C=/etc/tagdeflect/tagdeflect.toml
TOKEN=/etc/tagdeflect/token
LAB=/var/lib/tagdeflect-lab
FEED=/var/lib/tagdeflect/feed.jsonl
say() { echo "$*" | tee -a "$R" >/dev/console; }
check() { # check NAME STATUS DETAIL
  if [ "$2" = 0 ]; then say "PASS $1${3:+: $3}"; else say "FAIL $1${3:+: $3}"; fi
}
as() { local u=$1; shift; runuser -u "$u" -- "$@"; }
ms() { date +%s%3N; }
active_within() { # active_within SECONDS: until the unit is active
  local end=$(($(date +%s) + $1))
  while [ "$(date +%s)" -le $end ]; do
    [ "$(systemctl is-active tagdeflect)" = active ] && return 0
    sleep 0.2
  done
  return 1
}
# Feed lines carrying a frame of the vivid camera (its entry without "frame":false).
vivid_lines() { grep -o '{"name":"vivid"[^}]*}' "$1" 2>/dev/null | grep -vc '"frame":false'; }
test_field() { as alice tagdeflect test status 2>/dev/null | grep -o "\"$1\":\"[^\"]*\"" | head -1 | cut -d'"' -f4; }
t_start=$(date +%s)
say "INFO $(uname -r); $(systemctl --version | head -1); $(. /etc/os-release && echo "$PRETTY_NAME")"
say "INFO system up after $(cut -d' ' -f1 /proc/uptime) s; $(systemctl is-system-running)"

# --- The package, installed as a lab would.
deb=$(ls /vm-test/tagdeflect_*.deb | head -1)
cd /vm-test
t0=$(ms)
apt-get install -y --no-install-recommends "./$(basename "$deb")" >"$O/apt.log" 2>&1 </dev/null
st=$?
check "apt-get install ./$(basename "$deb") (booted systemd)" $st "$(($(ms) - t0)) ms; postinst said: $(grep -m1 '^tagdeflect: installed' "$O/apt.log")"
g=$(getent group tagdeflect)
[ -n "$g" ]; check "postinst made the group tagdeflect" $? "$g"
m=$(stat -c '%a %U %G' "$LAB" 2>&1)
[ "$m" = "2770 root tagdeflect" ]; check "postinst made $LAB" $? "$m"
[ "$(systemctl is-enabled tagdeflect 2>&1)" = disabled ]; check "the service is installed, not enabled" $? "$(systemctl is-enabled tagdeflect 2>&1)"

# --- The camera: vivid's capture node (webcam input), its group from udev.
modprobe vivid n_devs=1 node_types=0x1 >"$O/vivid.log" 2>&1
udevadm settle -t 10
i=0; while [ ! -e /dev/video0 ] && [ $i -lt 50 ]; do sleep 0.1; i=$((i + 1)); done
n=$(stat -c '%A %U %G' /dev/video0 2>&1)
[ -c /dev/video0 ]; check "vivid's /dev/video0" $? "$n, $(cat /sys/class/video4linux/video0/name 2>/dev/null)"
# vivid's buffer timestamps against the clock when they are dequeued (CLOCK_MONOTONIC; the VM
# never sleeps, so /proc/uptime is that clock): at 1 fps, how far ahead of its delivery vivid
# stamps a frame ("end of frame").
v4l2-ctl -d /dev/video0 --set-fmt-video=width=640,height=480 --set-parm=1 --stream-mmap --stream-count=3 --verbose \
  >"$O/vivid-stamps.log" 2>&1
up=$(cut -d' ' -f1 /proc/uptime)
ts=$(grep -o 'ts: [0-9.]*' "$O/vivid-stamps.log" | tail -1 | cut -d' ' -f2)
say "INFO vivid's last buffer stamped ${ts:-?} s (CLOCK_MONOTONIC), dequeued by ${up} s: $(awk -v a="${ts:-0}" -v b="$up" 'BEGIN { printf "%+.3f", a - b }') s; $(grep -o '(ts-[^)]*)' "$O/vivid-stamps.log" | tail -1)"

# --- The configuration, as the guide says: a fourth camera (V4L2), the lab's tests folder
# and its token; the sync tolerance widened so the real camera's frames may join the simulated
# cameras' sets.
#
# Fitted to an emulated CPU (TCG is 20-50x slower than the host): a simulated frame is
# stamped when due and handed over once rendered; when rendering takes longer than the wait
# for a set's missing cameras (one frame period of the fastest camera, crates/io's sync),
# vivid's newer set has closed by then and the simulated frame is dropped as late, by the
# assembler's contract (sets leave in time order). So the simulated rig is cut to its centre
# camera at SIM_FPS (1: the set wait becomes 1 s, vivid runs at 1 fps too) and renders
# without its optical blur (SIM_BLUR: the blur is most of a frame's rendering time); the
# render times of both settings are measured below and printed.
cp "$C" "$O/tagdeflect.toml.installed"
# rig_config FPS BLUR: the installed configuration turned into the VM's rig.
rig_config() {
  cp "$O/tagdeflect.toml.installed" "$C"
  sed -i 's/^tolerance_ms = .*/tolerance_ms = 100.0/' "$C"
  if [ "${SIM_CAMERAS:-3}" = 1 ]; then
    # The simulated rig cut to its centre camera (an emulated CPU renders and detects slowly).
    awk '
      function flush() { if (buf != "" && !drop) printf "%s", buf; buf = ""; drop = 0; inblock = 0 }
      /^\[/ { flush(); if ($0 == "[[camera]]") inblock = 1 }
      inblock { buf = buf $0 "\n"; if ($0 ~ /^name = "(left|right)"/) drop = 1; next }
      { print }
      END { flush() }' "$C" | sed '/^\[sim\]$/,/^\[/ s/^cameras = 3$/cameras = 1/' >"$C.new" && mv "$C.new" "$C"
  fi
  sed -i "s/^fps = 5.0$/fps = $1/" "$C"
  sed -i "/^\[sim\]$/,/^\[/ s/^blur_sigma = .*/blur_sigma = $2/" "$C"
  sed -i '/^\[output\]$/a tests = "/var/lib/tagdeflect-lab/tests"\nhttp_token_file = "/etc/tagdeflect/token"' "$C"
  cat >>"$C" <<'EOF'

# Added by the VM's check: the kernel's virtual camera (a test pattern: no tags).
[[camera]]
name = "vivid"
source = "v4l2:/dev/video0"
fps = 1.0
width = 640
height = 480
fx = 600.0
fy = 600.0
cx = 319.5
cy = 239.5
EOF
}
# render_s BLUR: seconds to render one simulated 640x480 frame here (`simulate`: 9 frame sets
# less 1, so the process's start is left out).
render_s() {
  local t1 t4 a
  a=$(ms); tagdeflect simulate --out /tmp/r1 --cameras 1 --width 640 --height 480 --frame-sets 1 --rest-frames 0 --fps 1 \
    --blur-sigma "$1" --frame-format pgm >/dev/null 2>&1; t1=$(($(ms) - a))
  a=$(ms); tagdeflect simulate --out /tmp/r4 --cameras 1 --width 640 --height 480 --frame-sets 9 --rest-frames 0 --fps 1 \
    --blur-sigma "$1" --frame-format pgm >/dev/null 2>&1; t4=$(($(ms) - a))
  rm -rf /tmp/r1 /tmp/r4
  awk -v a="$t1" -v b="$t4" 'BEGIN { printf "%.2f", (b - a) / 8000 }'
}
# sim_frames SINCE: "frames-in late median-age-ms" of the simulated camera (camera 0) in the
# service's journal since SINCE (the assembler's trace and debug lines: the drop-in below).
sim_frames() {
  local log n late med
  log=$(journalctl -u tagdeflect --since "$1" --no-pager -o cat 2>/dev/null)
  n=$(grep 'frame in' <<<"$log" | grep -c ' camera=0 ')
  late=$(( $(grep 'late frame:' <<<"$log" | grep -c ' camera=0 ') +
    $(grep 'late frames:' <<<"$log" | grep -o 'cameras=\[[0-9, ]*\]' | tr -c '0-9\n' ' ' | tr ' ' '\n' | grep -cx 0) ))
  med=$(grep 'frame in' <<<"$log" | grep ' camera=0 ' | grep -o 'age_ms=[-0-9.]*' | cut -d= -f2 | sort -g |
    awk '{ a[NR] = $1 } END { if (NR) printf "%.0f", a[int((NR + 1) / 2)]; else print "-" }')
  echo "$n $late $med"
}
# The assembler's per-frame lines (a frame's age when it arrives, late frames) in the journal.
mkdir -p /etc/systemd/system/tagdeflect.service.d
printf '[Service]\nEnvironment=TAGDEFLECT_LOG=info,tagdeflect_io::sync=trace\n' >/etc/systemd/system/tagdeflect.service.d/vm-sync-log.conf
systemctl daemon-reload
ri=$(render_s 0.6)
rf=$(render_s "${SIM_BLUR:-0.0}")
say "INFO one simulated 640x480 frame renders here in ${ri} s as installed (blur_sigma 0.6), ${rf} s fitted (blur_sigma ${SIM_BLUR:-0.0})"

sh -c 'umask 027; head -c 24 /dev/urandom | od -An -tx1 | tr -d " \n" > /etc/tagdeflect/token; echo >> /etc/tagdeflect/token'
chgrp tagdeflect "$TOKEN" && chmod 640 "$TOKEN"
useradd -m -s /bin/bash alice && usermod -aG tagdeflect alice
useradd -m -s /bin/bash bob
say "INFO users: $(id alice); $(id bob); token $(stat -c '%A %U %G' "$TOKEN")"

# The control: the previous settings (2 fps, the installed blur) for CONTROL_S seconds, to
# show what the fitted ones change (the simulated camera's frames, their age, the late ones).
if [ "${CONTROL_S:-60}" -gt 0 ]; then
  rig_config 2.0 0.6
  since=$(date '+%Y-%m-%d %H:%M:%S')
  systemctl start tagdeflect >"$O/control-start.log" 2>&1
  sleep "${CONTROL_S:-60}"
  read -r cn cl ca <<<"$(sim_frames "$since")"
  systemctl stop tagdeflect
  say "INFO control (simulated camera at 2 fps, blur_sigma 0.6, set wait 0.5 s): $cn frames in ${CONTROL_S:-60} s, $cl late, median age at arrival $ca ms"
  rm -f "$FEED"
fi
rig_config "${SIM_FPS:-1}.0" "${SIM_BLUR:-0.0}"
cp "$C" "$O/tagdeflect.toml"

# --- The service under its installed unit.
since_main=$(date '+%Y-%m-%d %H:%M:%S')
t0=$(ms)
systemctl enable --now tagdeflect >"$O/enable.log" 2>&1
st=$?
active_within 90
a=$?
[ $st = 0 ] && [ $a = 0 ]; check "systemctl enable --now tagdeflect: active (Type=notify)" $? "$(($(ms) - t0)) ms to active"
pid=$(systemctl show -p MainPID --value tagdeflect)
uid=$(awk '/^Uid:/{print $2}' /proc/"$pid"/status 2>/dev/null)
groups=$(awk '/^Groups:/{$1=""; print}' /proc/"$pid"/status 2>/dev/null)
gnames=$(for gid in $groups; do getent group "$gid" | cut -d: -f1; done | tr '\n' ' ')
user=$(getent passwd "$uid" | cut -d: -f1)
[ "$user" = tagdeflectd ] && echo " $gnames " | grep -q ' video ' && echo " $gnames " | grep -q ' tagdeflect '
check "runs as the dynamic user in video and tagdeflect" $? "uid $uid ($user), groups: $gnames"
say "INFO $(systemctl show -p DevicePolicy -p DeviceAllow -p UMask -p DynamicUser tagdeflect | tr '\n' ' ')"

# Frames of the vivid camera in the feed.
end=$(($(date +%s) + ${FRAMES_S:-240}))
while [ "$(vivid_lines "$FEED")" -lt 25 ] && [ "$(date +%s)" -le $end ]; do sleep 1; done
sleep 5
vl=$(vivid_lines "$FEED")
total=$(wc -l <"$FEED" 2>/dev/null || echo 0)
nd=$(grep -c '"net_deflection_mm"' "$FEED" 2>/dev/null)
open=$(ls -l /proc/"$pid"/fd 2>/dev/null | grep -c /dev/video0)
dropped=$(tail -1 "$FEED" | grep -o '{"name":"vivid"[^}]*}' | grep -o '"dropped_frames":[0-9]*' | cut -d: -f2)
[ "$vl" -ge 25 ] && [ "$open" -ge 1 ]
check "DevicePolicy=closed lets the V4L2 camera through: feed lines with vivid's frame" $? \
  "$vl of $total lines (in $(( $(ms) - t0 )) ms since start), $nd with net deflection (simulated cameras), /dev/video0 open $open time(s), vivid dropped ${dropped:-0}"
# Fewer late than in the control (same machine, same load, minutes apart), and at least 10 kept.
read -r sn sl sa <<<"$(sim_frames "$since_main")"
[ $((sn - sl)) -ge 10 ] && { [ "${CONTROL_S:-60}" = 0 ] || [ $((sl * ${cn:-0})) -lt $((${cl:-0} * sn)) ]; }
check "the simulated camera's frames join sets beside vivid's, fewer late than in the control" $? \
  "$sn frames in, $sl late, median age at arrival $sa ms (control: ${cn:-?} in, ${cl:-?} late, ${ca:-?} ms); $nd feed lines with a net deflection"
grep -i 'denied\|not permitted' <(journalctl -u tagdeflect -b --no-pager) | head -3 >"$O/denied.log"
[ ! -s "$O/denied.log" ]; check "no permission error in the service's journal" $? "$(head -1 "$O/denied.log")"

# DevicePolicy=closed, enforced: a root shell moved into the unit's cgroup (where the unit's
# device filter applies, whoever the process is) opens /dev/video0 and /dev/null, and is
# refused the disk and /dev/mem, which the same root shell opens outside the unit.
cg=/sys/fs/cgroup$(systemctl show -p ControlGroup --value tagdeflect)
in_unit() { sh -c 'echo $$ >"$1/cgroup.procs" && exec 3<"$2"' sh "$cg" "$1" 2>&1; }
outside() { sh -c 'exec 3<"$1"' sh "$1" 2>&1; }
dp=""
ok=0
for d in /dev/video0 /dev/null; do
  e=$(in_unit "$d") || { ok=1; e="refused: $e"; }
  dp="$dp $d in the unit: ${e:-opens};"
done
for d in /dev/vda /dev/mem; do
  o=$(outside "$d") || ok=1
  e=$(in_unit "$d") && ok=1
  echo "$e" | grep -q 'not permitted' || ok=1
  dp="$dp $d: outside ${o:-opens}, in the unit $(echo "${e:-opens}" | sed 's/^sh: [0-9]*: //');"
done
dp=${dp# }
check "DevicePolicy=closed refuses a device the unit does not allow, lets the camera through" $ok "${dp%;}"

# --- A lab user starts a test without sudo; a user outside the group cannot.
out=$(as alice tagdeflect test start --specimen B12 --operator alice --standard astm-c1609 --token-file "$TOKEN" 2>&1)
st=$?
check "alice (group tagdeflect) starts a test with the token file, no sudo" $st "$(echo "$out" | head -c 200)"
id=$(test_field id)
[ "$(test_field state)" = running ] && [ -n "$id" ]; check "the test runs" $? "id $id"
as bob cat "$TOKEN" >/dev/null 2>"$O/bob-token.err"
[ $? != 0 ]; check "bob (not in the group) cannot read the token" $? "$(head -1 "$O/bob-token.err")"
out=$(as bob tagdeflect test stop --token-file "$TOKEN" 2>&1)
st=$?
[ $st != 0 ] && [ "$(test_field state)" = running ]; check "bob's stop with the token file is refused" $? "exit $st: $(echo "$out" | head -c 160)"
as bob ls "$LAB/tests" >/dev/null 2>"$O/bob-ls.err"
[ $? != 0 ]; check "bob cannot list the tests" $? "$(head -1 "$O/bob-ls.err")"
sleep "$TEST_S"

# --- systemctl stop with a test running: a clean exit; start resumes the test.
lines_before=$(wc -l <"$LAB/tests/$id/feed.jsonl" 2>/dev/null || echo 0)
t0=$(ms)
systemctl stop tagdeflect
stop_ms=$(($(ms) - t0))
res=$(systemctl show -p Result --value tagdeflect)
code=$(systemctl show -p ExecMainCode --value tagdeflect)
status=$(systemctl show -p ExecMainStatus --value tagdeflect)
# ExecMainCode 1 = CLD_EXITED (exited by itself, not killed).
[ "$res" = success ] && [ "$code" = 1 ] && [ "$status" = 0 ]
check "systemctl stop during a test: a clean exit" $? "Result=$res, exit status $status (code $code), $stop_ms ms; the test's feed had $lines_before lines"
[ -f "$LAB/tests/.running.json" ] || ls -a "$LAB/tests" >"$O/tests-after-stop.txt"
[ -f "$LAB/tests/.running.json" ]; check "the running test's state is kept across the stop" $? "$(ls -a "$LAB/tests" | tr '\n' ' ')"
t0=$(ms)
systemctl start tagdeflect
active_within 90
sleep 3
[ "$(test_field state)" = running ] && [ "$(test_field id)" = "$id" ]
check "systemctl start resumes the test" $? "state $(test_field state), id $(test_field id), $(($(ms) - t0)) ms"
sleep 5
old=$(systemctl show -p MainPID --value tagdeflect)
t0=$(ms)
systemctl restart tagdeflect
active_within 90
sleep 3
new=$(systemctl show -p MainPID --value tagdeflect)
[ "$old" != "$new" ] && [ "$(test_field state)" = running ] && [ "$(test_field id)" = "$id" ]
check "systemctl restart resumes the test" $? "pid $old -> $new, state $(test_field state), $(($(ms) - t0)) ms"
journalctl -u tagdeflect -b --no-pager | grep -i 'resum' | tail -2 | sed 's/^/INFO journal: /' | tee -a "$R" >/dev/console
sleep "$TEST_S"

# --- The lab user stops the test and copies its folder and report.
t0=$(ms)
out=$(as alice tagdeflect test stop --token-file "$TOKEN" 2>&1)
st=$?
# Exit 3: the folder is complete but the report was not fit (a short simulated test) — said.
[ $st = 0 ] || [ $st = 3 ]; check "alice stops the test" $? "exit $st, $(($(ms) - t0)) ms: $(echo "$out" | head -c 240)"
T="$LAB/tests/$id"
perm=$(stat -c '%A %U %G' "$T" "$T/test.json" "$T/report/report.json" 2>&1 | tr '\n' ';')
[ -f "$T/test.json" ] && [ -f "$T/report/report.json" ]; check "the test folder has test.json and report/report.json" $? "$perm"
tl=$(wc -l <"$T/feed.jsonl" 2>/dev/null || echo 0)
tv=$(vivid_lines "$T/feed.jsonl")
td=$(grep -c '"net_deflection_mm"' "$T/feed.jsonl" 2>/dev/null)
[ "$tl" -gt "$lines_before" ] && [ "$tv" -ge 1 ]; check "the test's feed grew across the restarts, with vivid's frames" $? "$tl lines ($lines_before before the stop), $tv with vivid's frame, $td with a net deflection"
as alice cp -r "$T" /home/alice/ 2>"$O/alice-cp.err"
st=$?
n=$(find "/home/alice/$id" -type f 2>/dev/null | wc -l)
cmp -s "$T/report/report.json" "/home/alice/$id/report/report.json"
[ $st = 0 ] && [ $? = 0 ] && [ "$n" -ge 4 ]; check "alice copies the test folder and its report to her home" $? "$n files, $(du -sh "/home/alice/$id" 2>/dev/null | cut -f1); $(head -1 "$O/alice-cp.err")"
as bob cat "$T/test.json" >/dev/null 2>"$O/bob-cat.err"
[ $? != 0 ]; check "bob cannot read the test" $? "$(head -1 "$O/bob-cat.err")"
as alice tagdeflect report verify "$T" >"$O/verify.log" 2>&1
check "alice runs report verify on the test folder" $? "$(tail -1 "$O/verify.log" | head -c 160)"

# --- The unit as systemd sees it.
# --man=no: the VM has no man pages (the unit's Documentation= names systemd.exec(5)).
out=$(systemd-analyze verify --man=no /lib/systemd/system/tagdeflect.service 2>&1)
st=$?
[ $st = 0 ] && [ -z "$out" ]; check "systemd-analyze verify (installed unit, booted systemd)" $? "${out:-no complaints}"
systemd-analyze security tagdeflect.service --no-pager >"$O/security.txt" 2>&1
check "systemd-analyze security" $? "$(grep -i 'overall exposure' "$O/security.txt" | sed 's/^→ *//')"
say "INFO feed: $(wc -l <"$FEED") lines; service restarts: $(systemctl show -p NRestarts --value tagdeflect)"

systemctl stop tagdeflect
res=$(systemctl show -p Result --value tagdeflect)
status=$(systemctl show -p ExecMainStatus --value tagdeflect)
[ "$res" = success ] && [ "$status" = 0 ]; check "systemctl stop, no test running: a clean exit" $? "Result=$res, exit status $status"
journalctl -b --no-pager >"$O/journal.txt" 2>&1
journalctl -u tagdeflect -b --no-pager >"$O/tagdeflect-journal.txt" 2>&1
cp -r "$T" "$O/test" 2>/dev/null
cp "$FEED" "$O/service-feed.jsonl" 2>/dev/null
say "INFO checks took $(($(date +%s) - t_start)) s"
say "END"
sync
