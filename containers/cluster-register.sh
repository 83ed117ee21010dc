#!/bin/sh
# The compose cluster's registrations (compose.cluster.yaml, service "register"): each device is
# registered by a Set on one gateway, which then owns it; the others forward to it, and take it
# over when that gateway's container goes. Tried again each second until the gateways are up,
# for two minutes at most; a name already registered (a second run) counts as done.
set -u
for pair in gw1=thermo1 gw2=rover1 gw3=thermo2; do
  gateway=${pair%%=*}
  device=${pair#*=}
  tries=0
  until psctl -t "$gateway:50051" set registry "services.$device" "tcp://$device:7001" \
      || psctl -t "$gateway:50051" get registry "services.$device" >/dev/null 2>&1; do
    tries=$((tries + 1))
    if [ "$tries" -ge 120 ]; then
      echo "register: $device on $gateway: no gateway answered within 120 s" >&2
      exit 1
    fi
    sleep 1
  done
  echo "register: $device on $gateway"
done
