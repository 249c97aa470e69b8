#!/usr/bin/env bash
# Generate a DEVELOPMENT certificate authority plus router and client certificates for Zenoh TLS.
#
#   scripts/gen_dev_certs.sh OUT_DIR [--san NAME|IP]... [--client NAME]... [--days N] [--force]
#
# Writes into OUT_DIR (created if missing, mode 700):
#   ca.pem, ca-key.pem                 the CA (keep ca-key.pem offline in anything real)
#   router.pem, router-key.pem         router certificate, CN "router", serverAuth; its SAN holds
#                                      localhost, 127.0.0.1, ::1, router and every --san given
#   client-NAME.pem, client-NAME-key.pem
#                                      one client certificate per --client (CN = NAME, clientAuth),
#                                      for mutual TLS; default NAME list: robot-sensor geometry
#                                      gpu-semantic query-service query-client admin
#   .gitignore                         "*": nothing in OUT_DIR is ever committed by accident
# Keys are ECDSA P-256 (PKCS#8), private keys mode 600. Existing files are never overwritten
# unless --force is given. Production: use your organisation's CA; see docs/DEPLOY.md.
set -euo pipefail

usage() { sed -n '2,19p' "$0" >&2; exit 2; }
die() { printf 'gen_dev_certs.sh: %s\n' "$*" >&2; exit 1; }

[ $# -ge 1 ] || usage
case "$1" in -h|--help) usage ;; -*) die "first argument must be the output folder, got option '$1'" ;; esac
out_dir="$1"; shift
sans=("DNS:localhost" "IP:127.0.0.1" "IP:::1" "DNS:router")
clients=()
days=825
force=0
while [ $# -gt 0 ]; do
    case "$1" in
        --san)
            [ $# -ge 2 ] || die "--san needs a host name or IP address"
            if [[ "$2" =~ ^[0-9]+\.[0-9]+\.[0-9]+\.[0-9]+$ || "$2" == *:* ]]; then sans+=("IP:$2")
            elif [[ "$2" =~ ^[A-Za-z0-9]([A-Za-z0-9.-]*[A-Za-z0-9])?$ ]]; then sans+=("DNS:$2")
            else die "--san '$2' is neither a host name nor an IP address"; fi
            shift 2 ;;
        --client)
            [ $# -ge 2 ] || die "--client needs a name"
            [[ "$2" =~ ^[A-Za-z0-9][A-Za-z0-9_-]*$ ]] || die "--client '$2': use letters, digits, '-' or '_'"
            clients+=("$2"); shift 2 ;;
        --days)
            [ $# -ge 2 ] && [[ "$2" =~ ^[1-9][0-9]*$ ]] || die "--days needs a positive integer"
            days="$2"; shift 2 ;;
        --force) force=1; shift ;;
        -h|--help) usage ;;
        *) die "unknown argument '$1'" ;;
    esac
done
[ ${#clients[@]} -gt 0 ] || clients=(robot-sensor geometry gpu-semantic query-service query-client admin)
command -v openssl >/dev/null 2>&1 || die "openssl is not installed (apt-get install openssl)"

mkdir -p "$out_dir"
chmod 700 "$out_dir"
out_dir="$(cd "$out_dir" && pwd)"
umask 077

targets=(ca.pem ca-key.pem router.pem router-key.pem)
for name in "${clients[@]}"; do targets+=("client-$name.pem" "client-$name-key.pem"); done
if [ "$force" -eq 0 ]; then
    for f in "${targets[@]}"; do
        [ ! -e "$out_dir/$f" ] || die "$out_dir/$f exists; pass --force to replace every file"
    done
fi

work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT

new_key() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null; }

# 1. CA
new_key "$work/ca-key.pem"
openssl req -x509 -new -sha256 -key "$work/ca-key.pem" -days "$days" \
    -subj "/O=OpenFusion-Z development/CN=OpenFusion-Z dev CA" \
    -addext "basicConstraints=critical,CA:TRUE,pathlen:0" \
    -addext "keyUsage=critical,keyCertSign,cRLSign" \
    -addext "subjectKeyIdentifier=hash" \
    -out "$work/ca.pem"

# sign_leaf NAME CN EXTENDED_KEY_USAGE SAN
sign_leaf() {
    local name="$1" cn="$2" eku="$3" san="$4"
    new_key "$work/$name-key.pem"
    openssl req -new -sha256 -key "$work/$name-key.pem" -subj "/O=OpenFusion-Z development/CN=$cn" \
        -out "$work/$name.csr"
    cat > "$work/$name.ext" <<EOF
basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature,keyEncipherment
extendedKeyUsage=$eku
subjectKeyIdentifier=hash
authorityKeyIdentifier=keyid
subjectAltName=$san
EOF
    openssl x509 -req -sha256 -in "$work/$name.csr" -CA "$work/ca.pem" -CAkey "$work/ca-key.pem" \
        -CAcreateserial -days "$days" -extfile "$work/$name.ext" -out "$work/$name.pem" 2>/dev/null
    openssl verify -CAfile "$work/ca.pem" "$work/$name.pem" >/dev/null \
        || die "the generated $name certificate does not verify against the CA"
}

router_san="$(IFS=,; echo "${sans[*]}")"
sign_leaf router router serverAuth "$router_san"
for name in "${clients[@]}"; do
    sign_leaf "client-$name" "$name" clientAuth "DNS:$name"
done

for f in "${targets[@]}"; do
    install -m 600 "$work/$f" "$out_dir/$f"
done
chmod 644 "$out_dir/ca.pem" "$out_dir/router.pem"
for name in "${clients[@]}"; do chmod 644 "$out_dir/client-$name.pem"; done
printf '*\n' > "$out_dir/.gitignore"

printf 'gen_dev_certs.sh: wrote a development CA, router certificate (SAN %s) and %d client certificate(s) to %s\n' \
    "$router_san" "${#clients[@]}" "$out_dir" >&2
