#!/usr/bin/env bash
# The job's TLS files for deploy/k8s, made with openssl: a CA (ca.crt, ca.key) and one
# certificate signed by it (tls.crt, tls.key) that the coordinator and every worker
# present, as server and as client. Its names are those the pods dial:
# osrt-coordinator and osrt-workers-<i>.osrt-workers for i < WORKERS, plus any SAN given
# in openssl's form (DNS:name, IP:address).
#
#   deploy/make-certs.sh tls 2
#   kubectl create secret generic osrt-tls \
#       --from-file=tls/ca.crt --from-file=tls/tls.crt --from-file=tls/tls.key
#
# Keep ca.key out of the cluster and out of git: whoever has it can join the job.
set -euo pipefail
if [ $# -lt 2 ] || ! [[ $2 =~ ^[1-9][0-9]*$ ]]; then
    echo "usage: $0 OUT_DIR WORKERS [SAN ...]   (e.g. $0 tls 2)" >&2
    exit 2
fi
out=$1
workers=$2
shift 2
days=${OSRT_CERT_DAYS:-365}
command -v openssl >/dev/null || { echo "$0: openssl not found" >&2; exit 1; }
mkdir -p "$out"
umask 077

san="DNS:osrt-coordinator"
for ((i = 0; i < workers; i++)); do
    san+=",DNS:osrt-workers-$i.osrt-workers"
done
for extra in "$@"; do
    san+=",$extra"
done

openssl req -x509 -new -nodes -newkey ec -pkeyopt ec_paramgen_curve:P-256 \
    -keyout "$out/ca.key" -out "$out/ca.crt" -days "$days" -subj "/CN=osrt job CA" \
    -addext "basicConstraints=critical,CA:TRUE" \
    -addext "keyUsage=critical,keyCertSign,cRLSign" 2>/dev/null
openssl req -new -nodes -newkey ec -pkeyopt ec_paramgen_curve:P-256 \
    -keyout "$out/tls.key" -out "$out/tls.csr" -subj "/CN=osrt" 2>/dev/null
openssl x509 -req -in "$out/tls.csr" -CA "$out/ca.crt" -CAkey "$out/ca.key" \
    -CAcreateserial -days "$days" -out "$out/tls.crt" -extfile <(
        printf '%s\n' \
            "subjectAltName=$san" \
            "basicConstraints=critical,CA:FALSE" \
            "keyUsage=critical,digitalSignature" \
            "extendedKeyUsage=serverAuth,clientAuth"
    ) 2>/dev/null
rm -f "$out/tls.csr" "$out/ca.srl"
echo "$out: ca.crt, ca.key, tls.crt, tls.key for $san"
