"""Resolve configs and keys for every stage of a run, and say for each why it runs or is cached."""
from __future__ import annotations

import copy
import importlib
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import yaml
from pydantic import BaseModel, ValidationError

from pipeline.checkpoints import Checkpoints, summarize
from pipeline.errors import PipelineError
from pipeline.graph import ancestors, descendants, select, topo_order
from pipeline.keys import code_digest, stage_key
from pipeline.spec import PipelineSpec, allowed_keys, load_spec
from pipeline.store import Store

ENGINE_ROOT = Path(__file__).resolve().parent.parent  # the repo: holds pipeline/ and stages/


@dataclass
class Node:
    """One stage of one configuration, with its key and why it will (not) run."""

    stage: str
    module: str
    key: str
    config: dict[str, Any]  # canonical (validated, defaults filled) config section
    seed: int
    inputs: dict[str, str]  # needed stage -> its key
    key_inputs: dict[str, Any]  # everything the key was computed from
    label: str  # ref label: profile name or sweep point
    status: str = ""  # cached | run | invalid
    reasons: list[str] = field(default_factory=list)

    @property
    def short(self) -> str:
        return self.key[:12]


def parse_set(items: Sequence[str]) -> dict[str, dict[str, Any]]:
    """``['rl.reward=rule', 'collect.tasks=[push]']`` -> ``{'rl': {'reward': 'rule'}, 'collect': {...}}``."""
    out: dict[str, dict[str, Any]] = {}
    for item in items:
        if "=" not in item:
            raise PipelineError(f"--set {item!r}: expected stage.key=value")
        path, raw = item.split("=", 1)
        parts = path.strip().split(".")
        if len(parts) < 2 or not all(parts):
            raise PipelineError(f"--set {item!r}: expected stage.key=value (a dotted path with the stage first)")
        try:
            value = yaml.safe_load(raw) if raw.strip() else ""
        except yaml.YAMLError as e:
            raise PipelineError(f"--set {item!r}: value is not valid YAML ({e})") from None
        assign(out.setdefault(parts[0], {}), parts[1:], value)
    return out


def assign(d: dict, parts: list[str], value: Any) -> None:
    for p in parts[:-1]:
        d = d.setdefault(p, {})
    d[parts[-1]] = value


def deep_merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """``over`` on top of ``base``; nested mappings merge, everything else replaces."""
    out = copy.deepcopy(dict(base))
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def flatten(d: Any, prefix: str = "", scalars_only: bool = False) -> dict[str, Any]:
    """``{'a': {'b': 1}}`` -> ``{'a.b': 1}``; with ``scalars_only``, non-scalar leaves are dropped."""
    if isinstance(d, Mapping):
        out: dict[str, Any] = {}
        for k, v in d.items():
            out.update(flatten(v, f"{prefix}.{k}" if prefix else str(k), scalars_only))
        return out
    if scalars_only and not (isinstance(d, (int, float, str, bool)) or d is None):
        return {}
    return {prefix: d}


def _check_path(model: type[BaseModel], stage: str, parts: list[str], origin: str) -> None:
    """Raise if ``parts`` is not a key path of ``model`` (names the path and the allowed keys)."""
    cur: Any = model
    for i, p in enumerate(parts):
        if not (isinstance(cur, type) and issubclass(cur, BaseModel)):
            return
        fields = cur.model_fields
        if p not in fields:
            where = ".".join([stage, *parts[: i + 1]])
            raise PipelineError(f"{origin}: {where}: stage {stage!r} has no config key {p!r}; allowed keys: {allowed_keys(cur)}")
        cur = fields[p].annotation


class Project:
    """A loaded pipeline.yaml, its store and its stage modules."""

    def __init__(self, spec_path: str | Path = "pipeline.yaml", store: str | Path | None = None):
        self.spec_path = Path(spec_path).resolve()
        self.spec: PipelineSpec = load_spec(self.spec_path)
        self.base = self.spec_path.parent
        self.roots = [self.base] if self.base == ENGINE_ROOT else [self.base, ENGINE_ROOT]
        for r in self.roots:
            if str(r) not in sys.path:
                sys.path.insert(0, str(r))
        self.store = Store(Path(store) if store else self.base / self.spec.store)
        self.needs = {n: list(s.needs) for n, s in self.spec.stages.items()}
        self.order = topo_order(self.needs, source=str(self.spec_path))
        self._modules: dict[str, Any] = {}
        self._digests: dict[str, str] = {}

    # ---- stage modules -------------------------------------------------------------------------
    def module(self, stage: str):
        if stage not in self._modules:
            name = self.spec.stages[stage].module
            try:
                mod = importlib.import_module(name)
            except ModuleNotFoundError as e:
                raise PipelineError(f"stage {stage!r}: cannot import module {name!r} ({e}); is the stage implemented?") from None
            for attr in ("Config", "run"):
                if not hasattr(mod, attr):
                    raise PipelineError(f"stage {stage!r}: module {name!r} has no `{attr}` (the stage contract needs Config and run)")
            self._modules[stage] = mod
        return self._modules[stage]

    def used_needs(self, stage: str, cfg: BaseModel) -> list[str]:
        """The needs a stage reads under ``cfg``: all it declares but those its module's optional
        ``unread_needs(config)`` names (PPO in the simulator reads no play-tuned world model). A stage
        does not wait for, nor is its key made of, an input it does not read; a need added to
        pipeline.yaml is read unless the stage says otherwise."""
        declared = self.needs[stage]
        fn = getattr(self.module(stage), "unread_needs", None)
        unread = list(fn(cfg)) if fn is not None else []
        extra = [n for n in unread if n not in declared]
        if extra:
            raise PipelineError(f"stage {stage!r}: unread_needs names {', '.join(map(repr, extra))}, which "
                                f"{self.spec_path.name} does not list in stages.{stage}.needs ({', '.join(declared)})")
        return [n for n in declared if n not in unread]

    def digest(self, stage: str) -> str:
        if stage not in self._digests:
            self._digests[stage] = code_digest(self.spec.stages[stage].module, self.roots)
        return self._digests[stage]

    # ---- configs -------------------------------------------------------------------------------
    def profile_name(self, profile: str | None) -> str | None:
        if profile is None:
            return self.spec.default_profile
        if profile not in self.spec.profiles:
            raise PipelineError(f"--profile {profile!r}: unknown profile; known: {', '.join(self.spec.profiles) or '(none)'}")
        return profile

    def check_overrides(self, overrides: Mapping[str, Mapping[str, Any]], origin: str) -> None:
        """Fail early (before anything runs) on an override naming an unknown stage or key."""
        for stage, section in overrides.items():
            if stage not in self.spec.stages:
                raise PipelineError(f"{origin}: unknown stage {stage!r}; known stages: {', '.join(self.order)}")
            cfg_model = self.module(stage).Config
            for path in flatten(section):
                _check_path(cfg_model, stage, path.split("."), origin)

    def config(self, stage: str, profile: str | None, overrides: Mapping[str, Mapping[str, Any]]) -> BaseModel:
        """The stage's validated Config: yaml section, then profile overlay, then overrides."""
        raw = dict(self.spec.stages[stage].config)
        if profile is not None:
            raw = deep_merge(raw, self.spec.profiles[profile].get(stage, {}))
        raw = deep_merge(raw, overrides.get(stage, {}))
        try:
            return self.module(stage).Config.model_validate(raw)
        except ValidationError as e:
            lines = []
            for err in e.errors():
                loc = ".".join(str(p) for p in err["loc"])
                what = "unknown key" if err["type"] == "extra_forbidden" else err["msg"]
                lines.append(f"  {stage}.{loc}: {what}")
            src = f"{self.spec_path.name} (stages.{stage}.config" + (f" + profiles.{profile}.{stage}" if profile else "") + " + --set)"
            raise PipelineError(
                f"{src}: invalid config for stage {stage!r}:\n" + "\n".join(lines)
                + f"\n  allowed keys: {allowed_keys(self.module(stage).Config)}"
            ) from None

    # ---- planning ------------------------------------------------------------------------------
    def plan(
        self,
        stages: Sequence[str],
        profile: str | None,
        overrides: Mapping[str, Mapping[str, Any]],
        label: str,
        force: Sequence[str] = (),
    ) -> list[Node]:
        """Nodes for ``stages`` and everything they read under their configs (``used_needs``), in
        order, with status and reasons."""
        declared = set(stages)
        for s in stages:
            declared |= ancestors(self.needs, s)
        configs = {s: self.config(s, profile, overrides) for s in self.order if s in declared}
        used = {s: self.used_needs(s, cfg) for s, cfg in configs.items()}
        wanted, todo = set(stages), list(stages)
        while todo:
            for n in used[todo.pop()]:
                if n not in wanted:
                    wanted.add(n)
                    todo.append(n)
        keys: dict[str, str] = {}
        nodes: list[Node] = []
        for stage in self.order:
            if stage not in wanted:
                continue
            st = self.spec.stages[stage]
            cfg = configs[stage]
            cfg_json = cfg.model_dump(mode="json")
            inputs = {n: keys[n] for n in used[stage]}
            key_inputs = {"config": cfg_json, "code": self.digest(stage), "version": st.version, "inputs": inputs}
            key = stage_key(stage, st.version, key_inputs["code"], cfg_json, inputs)
            keys[stage] = key
            node = Node(stage, st.module, key, cfg_json, int(cfg_json.get("seed", 0) or 0), inputs, key_inputs, label)
            self._judge(node, force=stage in force)
            nodes.append(node)
        return nodes

    def _judge(self, node: Node, force: bool) -> None:
        look = self.store.lookup(node.stage, node.key)
        if look.state == "ok":
            node.status = "run" if force else "cached"
            node.reasons = ["forced"] if force else []
            return
        node.status = "run"
        self._judge_missing(node, look)
        resumable = Checkpoints(self.store.partial(node.stage, node.key)).names()
        if resumable:  # --force drops them before the stage starts (pipeline.execute)
            node.reasons.append(f"{'drops' if force else 'resumes from'} checkpoints: {summarize(resumable)}")

    def _judge_missing(self, node: Node, look) -> None:
        if look.state == "invalid":
            node.reasons = [f"invalid artifact, treated as missing: {look.problem}"]
            return
        ref = self.store.read_ref(node.label, node.stage)
        if ref is None:
            node.reasons = ["missing"]
            return
        old = ref.get("key_inputs", {})
        reasons = []
        a, b = flatten(old.get("config", {})), flatten(node.key_inputs["config"])
        changed = sorted(k for k in set(a) | set(b) if a.get(k, object()) != b.get(k, object()))
        if changed:
            reasons.append("config changed: " + ", ".join(f"{node.stage}.{k}" for k in changed))
        if old.get("code") != node.key_inputs["code"] or old.get("version") != node.key_inputs["version"]:
            reasons.append("code changed")
        ins = sorted(n for n in set(old.get("inputs", {})) | set(node.inputs) if old.get("inputs", {}).get(n) != node.inputs.get(n))
        if ins:
            reasons.append("input changed: " + ", ".join(ins))
        node.reasons = reasons or ["missing (artifact was removed)"]


def selection(project: Project, until: str | None, only: Sequence[str], start: str | None) -> list[str]:
    return select(project.needs, until=until, only=only, start=start)


def targets(project: Project, selected: Sequence[str], only: Sequence[str]) -> list[str]:
    """What a run plans for: the ``--only`` stages as given, else the selection's last stages (those no
    other selected stage needs); planning adds what they read, so a stage the selection names only
    as an ancestor drops out when no config reads it (``Project.used_needs``)."""
    chosen = set(selected)
    if only:
        return [s for s in selected if s in set(only)]
    return [s for s in selected if not (descendants(project.needs, s) & chosen)]
