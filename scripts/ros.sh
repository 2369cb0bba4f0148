#!/usr/bin/env bash
# `make ros` (part of `make install`): let the venv import Debian's ROS 1 Python packages (rospy,
# genpy, the message packages) without seeing the rest of /usr/lib/python3/dist-packages.
#
# Debian installs rospy for its own /usr/bin/python3 (3.11 on bookworm). The venv's Python must be
# the same major.minor version (the ROS packages are pure Python but for netifaces and PyYAML's
# optional C part, built for that ABI). This script links the top-level modules of the ROS Debian
# packages and of their Python dependencies (the python3-* closure of python3-rospy,
# python3-rosmaster, python3-roslaunch and the message packages) into VENV/coex-debian-ros/, and
# writes VENV/lib/pythonX.Y/site-packages/coex-debian-ros.pth naming that folder. A .pth folder
# comes AFTER site-packages on sys.path, and a module the venv already has is not linked at all:
# the venv's own numpy, yaml, dateutil ... always win; nothing else of dist-packages is visible.
#
# Never fails the build: without the Debian packages, or with another Python version, it says why
# and the ROS tests are skipped with that reason (tests/_ros.py). Usage: scripts/ros.sh [VENV_PYTHON]
set -u
PY=${1:-.venv/bin/python}
DIST=/usr/lib/python3/dist-packages
say() { echo "ros: $*"; }

VENV=$("$PY" -c 'import sys; print(sys.prefix)' 2>/dev/null) || { say "no Python at $PY"; exit 0; }
SITE=$("$PY" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
LINKS=$VENV/coex-debian-ros
PTH=$SITE/coex-debian-ros.pth

if [ ! -d "$DIST/rospy" ]; then
  rm -f "$PTH"
  say "Debian's rospy is not installed ($DIST/rospy): the ROS input, autonomy output and topside"
  say "products need it, and the ROS tests will be skipped (install: scripts/system-deps.sh, or"
  say "apt-get install python3-rospy python3-rosmaster python3-roslaunch python3-sensor-msgs python3-nav-msgs python3-geometry-msgs python3-std-msgs python3-tf2-msgs python3-rostopic python3-rosnode python3-rosbag)"
  exit 0
fi
WANT=$("$PY" -c 'import sys; print("%d.%d" % sys.version_info[:2])')
HAVE=$(/usr/bin/python3 -c 'import sys; print("%d.%d" % sys.version_info[:2])' 2>/dev/null || echo none)
if [ "$WANT" != "$HAVE" ]; then
  rm -f "$PTH"
  say "the venv runs Python $WANT, Debian's rospy is for Python $HAVE: not linked (make the venv with"
  say "Python $HAVE: make clean && make install PYTHON=/usr/bin/python3); the ROS tests will be skipped"
  exit 0
fi
if ! command -v dpkg-query >/dev/null 2>&1; then
  say "no dpkg-query: cannot tell which modules belong to ROS; not linked"; exit 0
fi

# the python3-* packages rospy and the message packages need, followed through Depends
ROOTS="python3-rospy python3-rosmaster python3-roslaunch python3-rosgraph python3-roslib python3-genpy
       python3-std-msgs python3-sensor-msgs python3-nav-msgs python3-geometry-msgs python3-tf2-msgs"
seen=" "
queue=$ROOTS
while [ -n "$(echo $queue)" ]; do
  set -- $queue; p=$1; shift; queue="$*"
  case "$seen" in *" $p "*) continue;; esac
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || continue
  seen="$seen$p "
  deps=$(dpkg-query -W -f='${Depends}' "$p" | tr ',' '\n' | sed 's/([^)]*)//g; s/|.*//; s/:any//; s/ //g' | grep '^python3-')
  queue="$queue $deps"
done
# every other installed *-msgs package too (actionlib_msgs, visualization_msgs ... when present)
for p in $(dpkg-query -W -f='${Package} ${Status}\n' 'python3-*-msgs' 2>/dev/null | awk '/install ok installed/ {print $1}'); do
  case "$seen" in *" $p "*) ;; *) seen="$seen$p ";; esac
done

rm -f "$PTH"              # the venv's own modules are judged without the links
names=""
for p in $seen; do
  names="$names $(dpkg -L "$p" 2>/dev/null | grep -E "^$DIST/[^/]+$" | tr '\n' ' ')"
done
# a module the venv already has stays the venv's (its numpy, yaml, setuptools ...): not linked
have=$("$PY" - $names <<'PYEOF'
import importlib.util, os, sys
for path in sys.argv[1:]:
    mod = os.path.basename(path).split(".")[0]
    if importlib.util.find_spec(mod) is not None:
        print(mod)
PYEOF
)
rm -rf "$LINKS.new"
mkdir -p "$LINKS.new"
linked=0
skipped=""
for path in $names; do
  name=$(basename "$path")
  case "$name" in *.egg-info|*.dist-info|*.pth|__pycache__) continue;; esac
  mod=${name%%.*}           # roman.py -> roman, netifaces.cpython-311-...so -> netifaces
  [ -e "$LINKS.new/$name" ] && continue
  if echo "$have" | grep -qx "$mod"; then
    case " $skipped " in *" $mod "*) ;; *) skipped="$skipped $mod";; esac
    continue
  fi
  ln -s "$path" "$LINKS.new/$name"
  linked=$((linked + 1))
done
rm -rf "$LINKS"
mv "$LINKS.new" "$LINKS"
echo "$LINKS" > "$PTH"
if "$PY" -c 'import rospy, genpy, sensor_msgs.msg, nav_msgs.msg, geometry_msgs.msg, std_msgs.msg' >/dev/null 2>&1; then
  say "the venv imports Debian's rospy ($linked modules linked from $DIST into $LINKS;"
  say "the venv's own kept:${skipped:- none})"
else
  say "linked $linked modules into $LINKS but the venv still cannot import rospy:"
  "$PY" -c 'import rospy, genpy, sensor_msgs.msg, nav_msgs.msg, geometry_msgs.msg, std_msgs.msg' 2>&1 | tail -n 3 | sed 's/^/  | /'
fi
exit 0
