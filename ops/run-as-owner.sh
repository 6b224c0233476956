#!/bin/sh
# run-as-owner.sh DIR COMMAND...: run COMMAND as the user and group that own DIR.
#
# The recorder's container starts it as root with the host's run folder mounted at DIR, so
# the run's files belong to whoever owns that folder on the host (the checkout's runs/, or
# the folder WAVEGRASP_RUNS names), whoever runs compose. WAVEGRASP_UID / WAVEGRASP_GID, if
# set, win. A uid other than 0 keeps no capability, and of the groups only that of /keys (this
# installation's logins, readable by their group: the service's own among them).
set -eu
dir=$1
shift
uid=${WAVEGRASP_UID:-$(stat -c %u "$dir")}
gid=${WAVEGRASP_GID:-$(stat -c %g "$dir")}
[ "$uid" = 0 ] || export HOME=/tmp  # root's home is not theirs
if [ -d /keys ]; then
  exec setpriv --reuid="$uid" --regid="$gid" --groups="$(stat -c %g /keys)" "$@"
fi
exec setpriv --reuid="$uid" --regid="$gid" --clear-groups "$@"
