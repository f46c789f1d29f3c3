# Sourced by the scripts that write VDB files: installs Debian's OpenVDB tools (vdb_tool,
# vdb_print) and Python binding, with numpy, when any is missing.
# shellcheck shell=bash
need_openvdb() {
    local py=/usr/bin/python3
    if command -v vdb_tool >/dev/null 2>&1 && command -v vdb_print >/dev/null 2>&1 \
        && "$py" -c 'import pyopenvdb, numpy' >/dev/null 2>&1; then
        return 0
    fi
    local sudo=""
    [ "$(id -u)" = 0 ] || sudo=sudo
    $sudo apt-get update
    $sudo apt-get install -y libopenvdb-tools python3-openvdb python3-numpy
}
