"""``occplug completion bash|zsh``: a shell completion script for commands, config references and ``type:`` names.

The script is generated once (``occplug completion bash > ~/.local/share/bash-completion/completions/occplug``)
and holds what it completes as data: every sub-command and its options (read from the argument parser), every
config reference a plugin ships (``queryocc/base``), and, for each place a component sits in a config (``data``,
``model.encoder``, ``model.heads.<name>``, ...), the registered names of its kind and the arguments those
components take. Completing is then plain shell, with no Python start-up (importing torch) per key press; files
and ``./configs`` recipes are listed when completing. Generate it again after installing or removing a plugin.

Completed: ``occplug <command>``, ``occplug config <action>``, options, ``-c <reference or file>``,
``model.enc<TAB>`` (override keys), ``model.encoder.type=<TAB>`` (the kind's registered names).
"""

from __future__ import annotations

import argparse
import re
import shlex
from pathlib import Path

from occplug.plugins import config_dirs, get_registry
from occplug.registry import Registry
from occplug.slots import TOP_LEVEL, Slot, component_params, slot_of

from .errors import UsageError

__all__ = ["add_parsers", "completion_data", "script"]

SHELLS = ("bash", "zsh")


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("completion", help="print a shell completion script (bash or zsh)")
    p.add_argument("shell", metavar="SHELL", help="bash or zsh")
    p.set_defaults(func=cmd_completion)


def _commands(parser: argparse.ArgumentParser, prefix: str = "") -> dict[str, list[str]]:
    """``{"": [commands], "fit": [options], "config": [actions], "config show": [options], ...}``."""
    out: dict[str, list[str]] = {}
    words: list[str] = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                words.append(name)
                out.update(_commands(child, f"{prefix} {name}".strip()))
        else:
            words += [s for s in action.option_strings if s.startswith("--") or len(s) == 2]
    out[prefix] = words
    return out


def _places(registry: Registry) -> dict[str, tuple[list[str], list[str]]]:
    """``{regex of a dotted key: (registered names, argument names)}`` for every place a component can sit.

    A named mapping or list of nodes (``model.heads``) matches any entry name or index; a place's arguments
    are those of every component of its kind (completion does not know which one a config picks).
    """
    out: dict[str, tuple[list[str], list[str]]] = {}

    def walk(pattern: str, slot: Slot, depth: int) -> None:
        node = pattern + r"\.[^.]+" if slot.mapping or slot.sequence else pattern
        if node in out or depth > 6:
            return
        names = registry.names(slot.kind)
        params: dict[str, Slot | None] = {}
        for name in names:
            for param, (_, annotation) in component_params(registry.get(slot.kind, name).factory).items():
                params.setdefault(param, slot_of(annotation))
        out[node] = (list(names), ["type", *sorted(params)])
        for param, nested in params.items():
            if nested is not None:
                walk(f"{node}\\.{re.escape(param)}", nested, depth + 1)

    for section, slot in TOP_LEVEL.items():
        if isinstance(slot, Slot):
            walk(f"^{re.escape(section)}", slot, 0)
    return {f"{k}$": v for k, v in out.items()}


def completion_data(parser: argparse.ArgumentParser, registry: Registry) -> dict[str, object]:
    """What the script completes: ``commands``, ``configs`` (plugin references), ``places`` (see :func:`_places`)."""
    configs = []
    for name, folder in sorted(config_dirs().items()):
        for path in sorted(Path(folder).rglob("*.yaml")):
            configs.append(f"{name}/{path.relative_to(folder).with_suffix('').as_posix()}")
    return {"commands": _commands(parser), "configs": configs, "places": _places(registry)}


_BODY = r"""
_occplug_words_of() {  # the words after command path $1 (sub-commands and options), or return 1
    local i
    for ((i = 0; i < ${#_occplug_cmd_keys[@]}; i++)); do
        if [[ "${_occplug_cmd_keys[i]}" == "$1" ]]; then
            _occplug_found=${_occplug_cmd_words[i]}
            return 0
        fi
    done
    return 1
}

_occplug_place_of() {  # the index of the component place dotted key $1 is, or return 1
    local i
    for ((i = 0; i < ${#_occplug_place_re[@]}; i++)); do
        if [[ "$1" =~ ${_occplug_place_re[i]} ]]; then
            _occplug_found=$i
            return 0
        fi
    done
    return 1
}

_occplug_filter() {  # COMPREPLY: the words after $1 that start with $1 (compgen -W, the same in bash and zsh)
    local prefix=$1 w
    shift
    COMPREPLY=()
    for w in "$@"; do [[ "$w" == "$prefix"* ]] && COMPREPLY+=("$w"); done
}

_occplug_complete() {
    [[ -n "${ZSH_VERSION:-}" ]] && emulate -L ksh  # 0-based arrays and word splitting, as in bash
    local line=${COMP_LINE:0:$COMP_POINT} cur="" prev="" cmd="" w i _occplug_found=""
    local -a words cands
    cands=()
    set -f
    words=($line)
    set +f
    if [[ "$line" != *[[:space:]] && ${#words[@]} -gt 0 ]]; then
        cur=${words[$((${#words[@]} - 1))]}
        words=("${words[@]:0:$((${#words[@]} - 1))}")
    fi
    ((${#words[@]} > 0)) && prev=${words[$((${#words[@]} - 1))]}
    for ((i = 1; i < ${#words[@]}; i++)); do
        w=${words[i]}
        [[ "$w" == -* || "$w" == *=* ]] && continue
        _occplug_words_of "${cmd:+$cmd }$w" && cmd="${cmd:+$cmd }$w"
    done
    if [[ "$prev" == "-c" || "$prev" == "--config" ]]; then
        cands=($_occplug_configs)
        for w in configs/*.yaml configs/*/*.yaml; do [[ -e "$w" ]] && cands+=("$w" "${w#configs/}"); done
        _occplug_filter "$cur" "${cands[@]}"
        [[ -z "${ZSH_VERSION:-}" ]] && COMPREPLY+=($(compgen -f -- "$cur"))  # zsh: complete -o default lists files
        return 0
    fi
    if [[ "$cur" == *=* ]]; then  # KEY=VALUE: the registered names of KEY's kind when KEY ends in .type
        local key=${cur%%=*}
        if [[ "$key" == *.type ]] && _occplug_place_of "${key%.type}"; then
            _occplug_filter "${cur#*=}" ${_occplug_place_names[_occplug_found]}
        fi
        return 0
    fi
    _occplug_words_of "$cmd"
    local subcommands="" options=""
    for w in $_occplug_found; do
        if [[ "$w" == -* ]]; then options+=" $w"; else subcommands+=" $w"; fi
    done
    if [[ "$cur" == -* ]]; then
        _occplug_filter "$cur" $options
        return 0
    fi
    if [[ -n "$subcommands" || "$cmd" == "" ]]; then
        _occplug_filter "$cur" $subcommands
        return 0
    fi
    [[ " $options " == *" -c "* ]] || return 0  # no config, no overrides: files (complete -o default)
    local parent=${cur%.*}
    if [[ "$cur" != *.* ]]; then
        cands=($_occplug_top)
    elif _occplug_place_of "$parent"; then
        for w in ${_occplug_place_args[_occplug_found]}; do
            if _occplug_place_of "$parent.$w"; then cands+=("$parent.$w."); else cands+=("$parent.$w="); fi
        done
    fi
    _occplug_filter "$cur" "${cands[@]}"
    type compopt > /dev/null 2>&1 && compopt -o nospace 2> /dev/null
    return 0
}
complete -o default -F _occplug_complete occplug
"""


def _array(name: str, items: list[str]) -> str:
    return f"{name}=({' '.join(shlex.quote(i) for i in items)})"


def script(shell: str, data: dict[str, object]) -> str:
    """The completion script for ``shell`` (zsh runs the bash function through ``bashcompinit``)."""
    commands: dict[str, list[str]] = data["commands"]  # type: ignore[assignment]
    places: dict[str, tuple[list[str], list[str]]] = data["places"]  # type: ignore[assignment]
    top = [f"{k}." if isinstance(v, Slot) else f"{k}=" for k, v in TOP_LEVEL.items()]
    lines = [
        f"# occplug {shell} completion, generated by `occplug completion {shell}`; generate again after adding a plugin",
    ]
    if shell == "zsh":
        lines.append("(( $+functions[compdef] )) || { autoload -U +X compinit && compinit }")
        lines.append("autoload -U +X bashcompinit && bashcompinit")
    lines += [
        _array("_occplug_cmd_keys", list(commands)),
        _array("_occplug_cmd_words", [" ".join(v) for v in commands.values()]),
        _array("_occplug_place_re", list(places)),
        _array("_occplug_place_names", [" ".join(v[0]) for v in places.values()]),
        _array("_occplug_place_args", [" ".join(v[1]) for v in places.values()]),
        f"_occplug_configs={shlex.quote(' '.join(data['configs']))}",  # type: ignore[arg-type]
        f"_occplug_top={shlex.quote(' '.join(top))}",
    ]
    return "\n".join(lines) + _BODY


def cmd_completion(args: argparse.Namespace) -> int:
    if args.shell not in SHELLS:
        raise UsageError(f"completion {args.shell}: unknown shell; expected one of {', '.join(SHELLS)}")
    from . import build_parser

    print(script(args.shell, completion_data(build_parser(), get_registry())), end="")
    return 0
