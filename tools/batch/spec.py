"""The batch spec (a YAML file or the command line) and the one function that builds its runs.

A spec names sequences (paths or globs), configurations (presets, YAML files, or either with
overrides), repeats and how every run plays (``speed`` or ``sequential``). :func:`build_tasks`
turns it into the list of :class:`BatchTask` that every engine executes: the order, the names and
each run's configuration are decided here and nowhere else.

YAML (every key but ``sequences`` optional)::

    sequences:                      # paths or globs; or {path, name, configs: [names]}
      - ~/data/euroc/V1_0*          # a glob: every match is a sequence
      - {path: room.mcap, name: room}
    configs:                        # presets, YAML files, or {name, base, set}
      - euroc-stereo-imu
      - {name: no-loop, base: euroc-stereo-imu, set: {loop_closure: false}}
      - {name: fewer, set: {frontend.max_features: 120}}   # base: slam run's default
    repeats: 3
    speed: max                      # or 1, 4 ...; or sequential: true (deterministic)
    cpus_per_run: 2
    timeout_s: 1800
    run_args: [--mesh]              # passed to every slam run
    path_map: {/home/me/data: /mnt/data}   # where Ray workers find the sequences
"""

from __future__ import annotations

import glob
import hashlib
import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from slam.core.errors import InputError, SlamError
from slam.core.messages import BatchTask

SPEC_KEYS = (
    "sequences",
    "configs",
    "repeats",
    "speed",
    "sequential",
    "cpus_per_run",
    "timeout_s",
    "run_args",
    "path_map",
)
#: Name of the configuration ``slam run`` picks by itself (by the sequence having an IMU).
DEFAULT_CONFIG = "default"


@dataclass(frozen=True)
class SequenceChoice:
    """A sequence of the batch: where it is, its name in tables, the configurations it gets."""

    path: Path
    name: str
    configs: tuple[str, ...] | None = None  # None: every configuration


@dataclass(frozen=True)
class ConfigChoice:
    """A configuration of the batch: a preset or YAML file (None: slam run's default), with
    overrides (dotted or nested keys)."""

    name: str
    base: str | None = None
    overrides: dict[str, Any] = field(default_factory=dict)


@dataclass
class BatchSpec:
    sequences: list[SequenceChoice]
    configs: list[ConfigChoice]
    repeats: int = 1
    speed: str = "max"
    sequential: bool = False
    cpus_per_run: float = 2.0
    timeout_s: float | None = None
    run_args: list[str] = field(default_factory=list)
    path_map: dict[str, str] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """The spec as YAML data (what ``OUT/batch.yaml`` holds), paths resolved."""
        return {
            "sequences": [
                {"path": str(s.path), "name": s.name}
                | ({"configs": list(s.configs)} if s.configs is not None else {})
                for s in self.sequences
            ],
            "configs": [
                {"name": c.name}
                | ({"base": c.base} if c.base else {})
                | ({"set": c.overrides} if c.overrides else {})
                for c in self.configs
            ],
            "repeats": self.repeats,
            "speed": self.speed,
            "sequential": self.sequential,
            "cpus_per_run": self.cpus_per_run,
            "timeout_s": self.timeout_s,
            "run_args": list(self.run_args),
            "path_map": dict(self.path_map),
        }


def safe_name(text: str) -> str:
    """A name usable as one folder name."""
    name = re.sub(r"[^A-Za-z0-9._+=-]+", "_", text).strip("._")
    return name or "unnamed"


def expand_sequences(entries: list[Any], base_dir: Path) -> list[SequenceChoice]:
    """Paths, globs or ``{path, name, configs}`` entries -> sequences with unique names.

    A relative path is relative to ``base_dir`` (the spec file's folder, or the working folder
    on the command line). A glob that matches nothing, or a path that does not exist, is an
    error: a batch does not silently shrink.
    """
    out: list[SequenceChoice] = []
    for entry in entries:
        name = configs = None
        if isinstance(entry, dict):
            unknown = set(entry) - {"path", "name", "configs"}
            if unknown or "path" not in entry:
                raise InputError(
                    f"a sequence entry takes path, name, configs; got {', '.join(map(str, entry))}"
                )
            text, name = str(entry["path"]), entry.get("name")
            configs = tuple(str(c) for c in entry["configs"]) if "configs" in entry else None
        else:
            text = str(entry)
        pattern = Path(text).expanduser()
        if not pattern.is_absolute():
            pattern = base_dir / pattern
        if glob.has_magic(str(pattern)):
            matches = [Path(p) for p in sorted(glob.glob(str(pattern)))]
            if not matches:
                raise InputError(f"sequence glob {text!r} matches nothing")
            if name is not None and len(matches) > 1:
                raise InputError(f"sequence {text!r}: a name for a glob of {len(matches)} paths")
        else:
            if not pattern.exists():
                raise InputError(f"{text}: no such sequence")
            matches = [pattern]
        for path in matches:
            out.append(
                SequenceChoice(path, name or (path.stem if path.is_file() else path.name), configs)
            )
    seen: dict[str, int] = {}
    unique = []
    for s in out:  # two sequences of one name (two V1_01 folders): the later ones get -2, -3
        n = seen[s.name] = seen.get(s.name, 0) + 1
        unique.append(s if n == 1 else SequenceChoice(s.path, f"{s.name}-{n}", s.configs))
    return unique


def nested(overrides: dict[str, Any]) -> dict[str, Any]:
    """Dotted keys (``frontend.max_features: 120``) as nested mappings."""
    out: dict[str, Any] = {}
    for key, value in overrides.items():
        parts = str(key).split(".")
        node = out
        for part in parts[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise InputError(f"config override {key!r} conflicts with {part!r}")
        if isinstance(value, dict):
            node.setdefault(parts[-1], {}).update(nested(value))
        else:
            node[parts[-1]] = value
    return out


def parse_configs(entries: list[Any], base_dir: Path) -> list[ConfigChoice]:
    """Preset names, YAML file paths, or ``{name, base, set}`` entries."""
    out = []
    for entry in entries:
        if isinstance(entry, dict):
            unknown = set(entry) - {"name", "base", "set"}
            if unknown:
                raise InputError(f"a config entry takes name, base, set; got {', '.join(unknown)}")
            base = entry.get("base")
            overrides = entry.get("set") or {}
            if not isinstance(overrides, dict):
                raise InputError(f"config {entry.get('name')!r}: 'set' must be a mapping of keys")
            name = entry.get("name") or (_base_name(base) if not overrides else None)
            if name is None:
                raise InputError("a config entry with 'set' needs a 'name'")
            out.append(ConfigChoice(str(name), _base_path(base, base_dir), dict(overrides)))
        else:
            out.append(ConfigChoice(_base_name(str(entry)), _base_path(str(entry), base_dir)))
    names = [c.name for c in out]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise InputError(f"two configurations named {dupes[0]!r}: give each a distinct name")
    return out


def _base_name(base: str | None) -> str:
    if base is None:
        return DEFAULT_CONFIG
    from slam.config import PRESETS

    return base if base in PRESETS else Path(base).stem


def _base_path(base: str | None, base_dir: Path) -> str | None:
    from slam.config import PRESETS

    if base is None or base in PRESETS:
        return base
    path = Path(base).expanduser()
    return str(path if path.is_absolute() else base_dir / path)


def load_spec(path: Path) -> BatchSpec:
    """A spec from a YAML file (unknown keys are errors)."""
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise InputError(f"{path}: cannot read the batch spec ({exc.strerror})") from None
    except yaml.YAMLError as exc:
        raise InputError(f"{path}: not valid YAML: {str(exc).splitlines()[0]}") from None
    if not isinstance(data, dict) or "sequences" not in data:
        raise InputError(f"{path}: a batch spec is a mapping with at least 'sequences'")
    unknown = sorted(set(data) - set(SPEC_KEYS))
    if unknown:
        raise InputError(f"{path}: unknown key {unknown[0]!r}; keys: {', '.join(SPEC_KEYS)}")
    base_dir = path.resolve().parent
    seqs = data["sequences"] if isinstance(data["sequences"], list) else [data["sequences"]]
    spec = BatchSpec(
        expand_sequences(seqs, base_dir),
        parse_configs(list(data.get("configs") or []), base_dir) or [ConfigChoice(DEFAULT_CONFIG)],
    )
    return apply_options(spec, data)


def apply_options(spec: BatchSpec, options: dict[str, Any]) -> BatchSpec:
    """``options`` (spec keys other than sequences/configs, None = keep) applied and checked."""
    if options.get("repeats") is not None:
        spec.repeats = _number(options["repeats"], "repeats", int, 1, 1000)
    if options.get("speed") is not None:
        speed = str(options["speed"])
        if speed != "max":
            _number(speed, "speed", float, 1e-3, 1e3)
        spec.speed = speed
    if options.get("sequential") is not None:
        spec.sequential = bool(options["sequential"])
    if options.get("cpus_per_run") is not None:
        spec.cpus_per_run = _number(options["cpus_per_run"], "cpus_per_run", float, 0.01, 1024)
    if options.get("timeout_s") is not None:
        spec.timeout_s = _number(options["timeout_s"], "timeout_s", float, 1.0, 1e6)
    if options.get("run_args") is not None:
        spec.run_args = [str(a) for a in options["run_args"]]
    if options.get("path_map") is not None:
        if not isinstance(options["path_map"], dict):
            raise InputError("path_map: a mapping of this machine's folder -> the workers' folder")
        spec.path_map = {str(k): str(v) for k, v in options["path_map"].items()}
    return spec


def _number(value: Any, key: str, kind: type, low: float, high: float) -> Any:
    try:
        number = kind(value)
    except (TypeError, ValueError):
        raise InputError(f"{key} must be a number, got {value!r}") from None
    if not low <= number <= high:
        raise InputError(f"{key} must be in [{low:g}, {high:g}], got {value!r}")
    return number


def resolve_config(choice: ConfigChoice) -> tuple[str | None, str | None]:
    """(``--config`` preset argument, YAML text) of a configuration, checked now (an unknown key
    or an out-of-range value fails the batch before any run, as it would fail `slam run`)."""
    from slam.config import PRESETS, config_from_dict

    if not choice.overrides:
        if choice.base is None or choice.base in PRESETS:
            return choice.base, None
    data: dict[str, Any] = {}
    if choice.base in PRESETS:
        data["preset"] = choice.base
    elif choice.base is not None:
        try:
            loaded = yaml.safe_load(Path(choice.base).read_text()) or {}
        except OSError:
            raise InputError(
                f"config {choice.base!r} is neither a preset ({', '.join(sorted(PRESETS))}) "
                "nor a YAML file"
            ) from None
        except yaml.YAMLError as exc:
            raise InputError(f"{choice.base}: not valid YAML: {exc}") from None
        if not isinstance(loaded, dict):
            raise InputError(f"{choice.base}: expected a mapping of config keys")
        data = loaded
    data = _merge(data, nested(choice.overrides))
    try:
        config_from_dict(data)
    except SlamError as exc:
        raise SlamError(f"configuration {choice.name!r}: {exc}") from None
    return None, yaml.safe_dump(data, sort_keys=False)


def _merge(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    out = dict(a)
    for key, value in b.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def worker_path(path: Path, path_map: dict[str, str]) -> str:
    """Where a worker reads ``path``: the longest ``path_map`` prefix replaced."""
    text = str(path)
    for local in sorted(path_map, key=len, reverse=True):
        prefix = local.rstrip("/")
        if text == prefix or text.startswith(prefix + "/"):
            return path_map[local].rstrip("/") + text[len(prefix) :]
    return text


def build_tasks(spec: BatchSpec) -> list[BatchTask]:
    """Every run of the batch, in order: repeat-major (repeat 1 of everything first, so a batch
    stopped early has every sequence x configuration once), then sequence, then configuration."""
    resolved = {c.name: resolve_config(c) for c in spec.configs}
    names = {c.name for c in spec.configs}
    run_args: tuple[str, ...] = (
        ("--sequential", "--speed", "max") if spec.sequential else ("--speed", spec.speed)
    )
    run_args += tuple(spec.run_args)
    tasks = []
    for repeat in range(1, spec.repeats + 1):
        for seq in spec.sequences:
            wanted = seq.configs if seq.configs is not None else [c.name for c in spec.configs]
            for name in wanted:
                if name not in names:
                    raise InputError(f"sequence {seq.name}: no configuration named {name!r}")
                config_arg, config_yaml = resolved[name]
                path = worker_path(seq.path.resolve(), spec.path_map)
                fingerprint = hashlib.sha256(
                    json.dumps([path, config_arg, config_yaml, run_args]).encode()
                ).hexdigest()[:16]
                tasks.append(
                    BatchTask(
                        run_id=f"{safe_name(seq.name)}/{safe_name(name)}/rep{repeat}",
                        sequence=seq.name,
                        sequence_path=path,
                        config=name,
                        config_arg=config_arg,
                        config_yaml=config_yaml,
                        repeat=repeat,
                        run_args=run_args,
                        timeout_s=spec.timeout_s,
                        fingerprint=fingerprint,
                    )
                )
    return tasks
