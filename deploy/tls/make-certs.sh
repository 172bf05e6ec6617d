#!/bin/sh
# A private certificate authority, a router certificate and (for mutual TLS) a client
# certificate for tagswarm across machines (ECDSA P-256 keys).  See docs/security.md.
#
#   deploy/tls/make-certs.sh DIR ROUTER_HOST [ROUTER_IP]
#   e.g. deploy/tls/make-certs.sh deploy/secrets/tls router.lab 192.168.1.10
#
# Writes DIR/ca.pem (give it to every machine), DIR/ca.key (keep it offline: it can
# sign anything), DIR/router.pem + router.key (the router only) and DIR/client.pem +
# client.key (clients, for mutual TLS).  The router certificate is valid for
# ROUTER_HOST, "localhost", 127.0.0.1 and ROUTER_IP if given: clients must connect
# to one of those names (tls/<name>:7447) or the handshake fails.  Existing files
# are not overwritten.
set -eu
dir=${1:?usage: make-certs.sh DIR ROUTER_HOST [ROUTER_IP]}
host=${2:?usage: make-certs.sh DIR ROUTER_HOST [ROUTER_IP]}
ip=${3:-}
days=825
mkdir -p "$dir"
chmod 700 "$dir"
cd "$dir"
umask 077

if [ ! -e ca.pem ]; then
  openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -sha256 -nodes -days 3650 -keyout ca.key -out ca.pem \
    -subj "/CN=tagswarm CA" -addext "basicConstraints=critical,CA:TRUE" \
    -addext "keyUsage=critical,keyCertSign,cRLSign"
fi

san="DNS:$host,DNS:localhost,IP:127.0.0.1"
[ -n "$ip" ] && san="$san,IP:$ip"

sign() {  # name, common name, extended key usage, subjectAltName (may be empty)
  [ -e "$1.pem" ] && return 0
  openssl req -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -sha256 -nodes -keyout "$1.key" -out "$1.csr" -subj "/CN=$2"
  {
    echo "basicConstraints=CA:FALSE"
    echo "keyUsage=critical,digitalSignature"
    echo "extendedKeyUsage=$3"
    [ -n "$4" ] && echo "subjectAltName=$4"
  } > "$1.ext"
  openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -days "$days" -sha256 \
    -extfile "$1.ext" -out "$1.pem"
  rm -f "$1.csr" "$1.ext"
}

sign router "$host" serverAuth "$san"
sign client "tagswarm-client" clientAuth ""
chmod 644 ca.pem router.pem client.pem
echo "written in $dir: ca.pem ca.key router.pem router.key client.pem client.key"
