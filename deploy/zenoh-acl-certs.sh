#!/usr/bin/env bash
# Certificates for the zenoh access-control sample (deploy/zenoh-acl-router.json5): a private CA and
# one key + certificate per node.  The ACL identifies a node by its certificate's common name (CN):
# irtrack-camera, irtrack-daemon, irtrack-ground (irtrack-router is the router's own).
# Run once, on a trusted machine; keep ca.key off the vehicle.  Needs the openssl command.
#
#   VEHICLE_DNS=uav1.irtrack.lan VEHICLE_IP=192.168.144.10 bash deploy/zenoh-acl-certs.sh OUT_DIR [EXTRA_CN...]
#
# EXTRA_CN: more nodes to make (tests/test_zenoh_acl.py adds an "irtrack-intruder" signed by the same
# CA: authenticated, but named by no ACL subject).
set -euo pipefail
out="${1:?usage: zenoh-acl-certs.sh OUT_DIR [EXTRA_CN...]}"
shift
VEHICLE_DNS="${VEHICLE_DNS:-uav1.irtrack.lan}"   # the name the clients dial (the router's certificate)
VEHICLE_IP="${VEHICLE_IP:-192.168.144.10}"
DAYS="${DAYS:-825}"
mkdir -p "$out"
cd "$out"
umask 077
openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -days "$DAYS" \
    -subj "/CN=irtrack CA" -keyout ca.key -out ca.pem 2>/dev/null
for cn in irtrack-router irtrack-camera irtrack-daemon irtrack-ground "$@"; do
    node="${cn#irtrack-}"
    openssl req -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes \
        -subj "/CN=$cn" -keyout "$node.key" -out "$node.csr" 2>/dev/null
    # rustls (zenoh 1.x) checks the name the client dials against subjectAltName, never the CN
    printf 'subjectAltName=DNS:%s,IP:%s\nextendedKeyUsage=serverAuth,clientAuth\n' \
        "$VEHICLE_DNS" "$VEHICLE_IP" > "$node.ext"
    openssl x509 -req -in "$node.csr" -CA ca.pem -CAkey ca.key -CAcreateserial \
        -days "$DAYS" -extfile "$node.ext" -out "$node.pem" 2>/dev/null
    rm -f "$node.csr" "$node.ext"
done
chmod 0444 ./*.pem
echo "made $(ls ./*.pem | wc -l) certificates in $PWD"
