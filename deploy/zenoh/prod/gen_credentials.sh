#!/usr/bin/env bash
# Generate user/password credentials for the production Zenoh router and its clients.
#
#   deploy/zenoh/prod/gen_credentials.sh OUT_DIR [--force]
#
# Writes into OUT_DIR (created if missing, mode 700; every file mode 600):
#   credentials.txt           the router's dictionary: one `identity:password` line per identity
#                             (router.json5 reads it as /etc/openfusion/secrets/credentials.txt)
#   client-IDENTITY.json5     a copy of deploy/zenoh/prod/client-IDENTITY.json5 with the
#                             generated password in place of the CHANGE-ME placeholder
#   .gitignore                "*": nothing here is ever committed by accident
# Identities: robot-sensor geometry gpu-semantic query-service query-client admin.
# Passwords are 32 random characters from openssl. Existing files are never overwritten unless
# --force is given (which rotates every password: restart the router and all clients).
set -euo pipefail

usage() { sed -n '2,15p' "$0" >&2; exit 2; }
die() { printf 'gen_credentials.sh: %s\n' "$*" >&2; exit 1; }

[ $# -ge 1 ] || usage
case "$1" in -h|--help) usage ;; -*) die "first argument must be the output folder, got option '$1'" ;; esac
out_dir="$1"; shift
force=0
while [ $# -gt 0 ]; do
    case "$1" in
        --force) force=1; shift ;;
        *) die "unknown argument '$1'" ;;
    esac
done
command -v openssl >/dev/null 2>&1 || die "openssl is not installed (apt-get install openssl)"

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
identities=(robot-sensor geometry gpu-semantic query-service query-client admin)

targets=(credentials.txt)
for ident in "${identities[@]}"; do
    template="$here/client-$ident.json5"
    [ -f "$template" ] || die "template $template is missing"
    grep -q 'password: "CHANGE-ME"' "$template" || die "template $template has no 'password: \"CHANGE-ME\"' line"
    targets+=("client-$ident.json5")
done

mkdir -p "$out_dir"
chmod 700 "$out_dir"
if [ "$force" -eq 0 ]; then
    for f in "${targets[@]}"; do
        [ ! -e "$out_dir/$f" ] || die "$out_dir/$f exists; pass --force to rotate every password"
    done
fi
umask 077

work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
: > "$work/credentials.txt"
for ident in "${identities[@]}"; do
    # 24 random bytes -> 32 base64 characters; '/' and '+' mapped so the value needs no quoting.
    password="$(openssl rand -base64 24 | tr '/+' '_-')"
    [ ${#password} -eq 32 ] || die "could not generate a password"
    printf '%s:%s\n' "$ident" "$password" >> "$work/credentials.txt"
    sed "s|password: \"CHANGE-ME\"|password: \"$password\"|" "$here/client-$ident.json5" \
        > "$work/client-$ident.json5"
done
for f in "${targets[@]}"; do
    install -m 600 "$work/$f" "$out_dir/$f"
done
printf '*\n' > "$out_dir/.gitignore"
printf 'gen_credentials.sh: wrote credentials.txt and %d client configs to %s\n' \
    "${#identities[@]}" "$(cd "$out_dir" && pwd)" >&2
