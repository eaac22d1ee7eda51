#!/usr/bin/env bash
# bootstrap.sh - make sure the repository's .venv exists and holds `pip install -e '.[dev]'` at the
# exact versions of constraints.txt (pyproject.toml declares ranges; CI and tools/run-cell run the
# pinned set).
#
# Source it (`. tools/bootstrap.sh`) from bash, or run it. Idempotent: the virtual environment is
# created with `python3 -m venv` only when .venv/bin/python is missing or broken, and pip runs only
# when pyproject.toml or constraints.txt differs from the last successful install (their SHA-256
# is kept in .venv/.chcos-bootstrap.sha256). Concurrent callers are serialised with flock on this file.
# On success it exports CHCOS_ROOT (the repository) and CHCOS_VENV (its .venv).
#
# Environment: CHCOS_PYTHON picks the interpreter that creates the venv (default python3, which
# must be 3.11 or newer). Needs network access to PyPI only when it installs.

chcos_bootstrap() {
    local root venv py stamp want have lockfd rc
    root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd -P) || return 1
    venv=$root/.venv
    py=${CHCOS_PYTHON:-python3}
    stamp=$venv/.chcos-bootstrap.sha256

    if [[ ! -f $root/pyproject.toml ]]; then
        echo "bootstrap: $root/pyproject.toml not found" >&2
        return 1
    fi
    exec {lockfd}<"${BASH_SOURCE[0]}" || return 1
    if ! flock "$lockfd"; then
        exec {lockfd}<&-
        echo "bootstrap: cannot lock ${BASH_SOURCE[0]}" >&2
        return 1
    fi

    rc=0
    if ! "$venv/bin/python" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; then
        if ! command -v "$py" >/dev/null; then
            echo "bootstrap: $py not found; install Python 3.11 or newer (Debian: python3 python3-venv)" >&2
            rc=1
        elif ! "$py" -c 'import sys; sys.exit(sys.version_info < (3, 11))'; then
            echo "bootstrap: $py is $("$py" -V 2>&1); chcos needs Python 3.11 or newer" >&2
            rc=1
        elif ! "$py" -m venv --clear "$venv"; then
            echo "bootstrap: '$py -m venv $venv' failed (Debian: apt-get install python3-venv)" >&2
            rc=1
        else
            rm -f -- "$stamp"
        fi
    fi

    if ((rc == 0)); then
        want=$(cat "$root/pyproject.toml" "$root/constraints.txt" | sha256sum) \
            && want=${want%% *} || rc=1
    fi
    if ((rc == 0)); then
        have=$(cat -- "$stamp" 2>/dev/null) || have=
        if [[ $have != "$want" ]]; then
            echo "bootstrap: installing chcos and its dev dependencies into $venv" >&2
            # pip's and the build backend's chatter goes to a log, shown only when pip fails.
            if (cd "$root" && "$venv/bin/python" -m pip install --quiet --disable-pip-version-check \
                    --editable '.[dev]' --constraint constraints.txt) \
                    >"$venv/.chcos-bootstrap.log" 2>&1; then
                printf '%s\n' "$want" >"$stamp.tmp" && mv -f -- "$stamp.tmp" "$stamp" || rc=1
            else
                cat -- "$venv/.chcos-bootstrap.log" >&2
                echo "bootstrap: pip install -e '.[dev]' -c constraints.txt failed (log:" \
                     "$venv/.chcos-bootstrap.log)" >&2
                rc=1
            fi
        fi
    fi

    exec {lockfd}<&-
    if ((rc == 0)); then
        export CHCOS_ROOT=$root CHCOS_VENV=$venv
    fi
    return "$rc"
}

if [[ ${BASH_SOURCE[0]} == "$0" ]]; then
    chcos_bootstrap
    exit
fi
chcos_bootstrap
