#!/usr/bin/env bash
# Install the Debian packages CoEx needs when they are missing (OpenJPEG for glymur; Chromium for
# the browser tests of the web console; ROS 1 for the ros input, autonomy output and topside
# products: roscore, rospy and the standard messages). Uses apt when it can (root or passwordless
# sudo); otherwise prints the exact command to run and exits 0 so that the rest of the install
# goes on. COEX_BROWSER_TESTS=0 skips Chromium, COEX_ROS=0 skips ROS. ROS is installed apart from
# the others: a distribution without Debian's ROS packages still gets the rest. ROS means roscore,
# rospy, the message packages CoEx uses and the command-line tools (rostopic, rosnode, rosbag).
set -u
want=()
if ! ldconfig -p 2>/dev/null | grep -q 'libopenjp2\.so\.7'; then
  want+=(libopenjp2-7)
fi
if [ "${COEX_BROWSER_TESTS:-1}" != 0 ] && ! command -v chromium >/dev/null 2>&1; then
  want+=(chromium)
fi
# rospy, roscore and the messages CoEx reads and writes (tf2-msgs: the ship's /tf), and the
# command-line tools docs/deploy.md uses on both computers (rostopic, rosnode, rosbag)
ROS_PACKAGES=(python3-rospy python3-rosmaster python3-roslaunch python3-sensor-msgs python3-nav-msgs
              python3-geometry-msgs python3-std-msgs python3-tf2-msgs python3-rostopic python3-rosnode
              python3-rosbag)
ros=()
if [ "${COEX_ROS:-1}" != 0 ] && { ! command -v roscore >/dev/null 2>&1 || [ ! -d /usr/lib/python3/dist-packages/rospy ] \
     || [ ! -d /usr/lib/python3/dist-packages/nav_msgs ] || [ ! -d /usr/lib/python3/dist-packages/tf2_msgs ] \
     || ! command -v rostopic >/dev/null 2>&1 || ! command -v rosnode >/dev/null 2>&1 \
     || ! command -v rosbag >/dev/null 2>&1; }; then
  ros=("${ROS_PACKAGES[@]}")
fi
[ ${#want[@]} -eq 0 ] && [ ${#ros[@]} -eq 0 ] && exit 0

all=("${want[@]}" "${ros[@]}")
if ! command -v apt-get >/dev/null 2>&1; then
  echo "CoEx needs: ${all[*]} (Debian/Ubuntu package names). Install them with your package manager." >&2
  exit 0
fi
if [ "$(id -u)" = 0 ]; then
  SUDO=""
elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
  SUDO="sudo"
else
  echo "CoEx needs Debian packages: run   sudo apt-get update && sudo apt-get install -y ${all[*]}" >&2
  exit 0
fi
$SUDO apt-get update -qq >/dev/null 2>&1 || true
install() {
  echo "installing Debian packages: $*"
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "$@" >/dev/null \
    || echo "apt-get could not install $*; run: sudo apt-get install -y $*" >&2
}
[ ${#want[@]} -gt 0 ] && install "${want[@]}"
if [ ${#ros[@]} -gt 0 ]; then
  if apt-cache show python3-rospy >/dev/null 2>&1; then
    install "${ros[@]}"
  else
    echo "ROS 1 is not in this distribution's packages (Debian bookworm has it): the ros input, autonomy" >&2
    echo "output and topside products need rospy (docs/deploy.md); their tests will be skipped" >&2
  fi
fi
exit 0
