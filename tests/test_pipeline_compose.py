"""docker-compose.yml and the Dockerfile, checked without a Docker engine: the YAML's structure, and every
service's command parsed by posegrid's own command-line parser."""

from __future__ import annotations

import re

import pytest

from conftest import ROOT
from services.cli import build_parser

yaml = pytest.importorskip(
    "ruamel.yaml", reason="no YAML parser installed (ruamel.yaml); cannot check the compose file"
)

EXPECTED = {"router", "source", "slam", "mapper0", "mapper1", "api"}


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.YAML(typ="safe", pure=True).load((ROOT / "docker-compose.yml").read_text())


def subcommands() -> set[str]:
    parser = build_parser()
    return set(next(a for a in parser._actions if a.dest == "command").choices)


def test_services_come_from_one_image_built_by_the_repo_dockerfile(compose):
    services = compose["services"]
    assert set(services) == EXPECTED
    for name, service in services.items():
        assert service["image"] == "posegrid:latest", name
        assert service["build"] == {"context": ".", "dockerfile": "Dockerfile"}, name
        assert service["stop_signal"] == "SIGINT", name
    dockerfile = (ROOT / "Dockerfile").read_text()
    assert re.search(r'^ENTRYPOINT \["posegrid"\]$', dockerfile, re.M)
    for package in ("mapping", "slam", "schemas", "services"):
        assert re.search(rf"^COPY {package} ", dockerfile, re.M), package


def test_everything_joins_through_the_router(compose):
    services = compose["services"]
    assert services["router"]["command"][:1] == ["router"]
    listen = services["router"]["command"][services["router"]["command"].index("--listen") + 1]
    port = listen.rsplit(":", 1)[1]
    for name, service in services.items():
        if name == "router":
            continue
        command = service["command"]
        assert command[command.index("--connect") + 1] == f"tcp/router:{port}", name
        assert "router" in service["depends_on"], name


def test_two_mapper_shards_split_the_map(compose):
    shards = []
    for name in ("mapper0", "mapper1"):
        command = compose["services"][name]["command"]
        shards.append((int(command[command.index("--shard") + 1]), int(command[command.index("--shards") + 1])))
    assert sorted(shards) == [(0, 2), (1, 2)]
    source = compose["services"]["source"]["command"]
    assert source[source.index("--wait-mappers") + 1] == "2" and "--wait-slam" in source


@pytest.mark.parametrize("service", sorted(EXPECTED))
def test_every_command_is_accepted_by_the_cli(compose, service):
    command = compose["services"][service]["command"]
    if command[0] not in subcommands():
        pytest.skip(f"`posegrid {command[0]}` is not part of this build yet (the {service} service needs it)")
    args = build_parser().parse_args(command)
    assert args.func is not None


def test_each_mapper_keeps_its_store_on_a_volume_of_its_own(compose):
    """A shard's container restarted (or the stack taken down and up) comes back with its map: its --state-dir lies
    on a named volume that no other service mounts, in a folder the image makes for the user it runs as."""
    services = compose["services"]
    declared = set(compose.get("volumes") or {})
    dockerfile = (ROOT / "Dockerfile").read_text()
    user = re.search(r"^USER (\S+)$", dockerfile, re.M)
    assert user is not None
    volumes_used = []
    for name in ("mapper0", "mapper1"):
        command = services[name]["command"]
        assert "--state-dir" in command, f"{name} keeps its map in memory only"
        state_dir = command[command.index("--state-dir") + 1]
        mounts = [m.split(":") for m in services[name].get("volumes", [])]
        holding = [(volume, target) for volume, target, *_ in mounts if state_dir.startswith(target.rstrip("/") + "/")]
        assert len(holding) == 1, f"{name}'s --state-dir {state_dir} is on no volume"
        volume, target = holding[0]
        assert volume in declared, f"{name} mounts {volume}, which is no named volume"
        volumes_used.append(volume)
        assert re.search(rf"mkdir -p {re.escape(target)}\b.*chown {user.group(1)}", dockerfile, re.S), target
    assert len(set(volumes_used)) == len(volumes_used), "two shards share a volume"
    for name, service in services.items():
        if name not in ("mapper0", "mapper1"):
            assert not {m.split(":")[0] for m in service.get("volumes", [])} & set(volumes_used), name
