#!/usr/bin/env bash
# The stablecues ROS 2 node without a robot and without a ROS install: replay a ROS 2 bag's camera
# to the node over DDS and print the loops it closes, as a ROS 2 graph of three processes
# (publisher, node, subscriber), launched by hand, no launch file.
#
#   pip install "stablecues[ros2]"
#   examples/ros2_replay.sh BAG [IMAGE_TOPIC [RIGHT_TOPIC]]
#   examples/ros2_replay.sh v101_bag /cam0/image_raw /cam1/image_raw       # a stereo pair
#   PRESET=default NODE_ARGS="--map map.sqlite" examples/ros2_replay.sh BAG  # a map kept, continued
#
# Everything stays on this computer: Cyclone DDS is configured to the loopback interface, no
# multicast, peer 127.0.0.1 (the configuration stablecues ships). ROS_DOMAIN_ID picks the domain.
# Each accepted loop is printed as one line of JSON; the node's summary (frames decided, skipped
# while busy, malformed) comes last.
set -euo pipefail

bag=${1:?usage: ros2_replay.sh BAG [IMAGE_TOPIC [RIGHT_TOPIC]]}
image=${2:-/cam0/image_raw}
right=${3:-}
preset=${PRESET:-fast}
read -r -a node_args <<< "${NODE_ARGS:-}"
if [ -n "$right" ]; then node_args+=(--right "$right"); fi

CYCLONEDDS_URI=$(python3 -c 'from stablecues.ros2.dds import LOOPBACK_CONFIG; print(LOOPBACK_CONFIG.as_uri())')
export CYCLONEDDS_URI
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-0}

pids=()
trap 'for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done' EXIT

# the subscriber: every accepted loop, as the robot's back end would receive it
stablecues ros2 echo --accepted &
pids+=($!)
# the node: the camera in, a decision per frame out; it exits 3 s after the last frame
stablecues ros2 --image "$image" --preset "$preset" --exit-after-idle 3 "${node_args[@]}" &
node=$!
pids+=("$node")
# the camera: the bag at its recorded rate, once the node has subscribed
stablecues ros2 play "$bag" --wait-subscribers 1 --wait-timeout 60
wait "$node"
