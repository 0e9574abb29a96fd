"""Every command the project prints for its users works as printed.

README.md, docs/*.md, and the comments of docker-compose.yml, the Dockerfile and lab/'s
files are searched for servotune, docker and docker-compose commands
(tests/support/doc_commands.py); each recipe is then run as its user would, in order, through
the CLI's own argparse parser and against docker-compose.yml (tests/support/recipe_check.py):
no Docker needed. The checks are proven to fail on recipes that were once printed broken.
"""

from __future__ import annotations

import pytest

from tests.support.doc_commands import (
    ROOT,
    Printed,
    Recipe,
    all_printed,
    comments,
    markdown,
    split_command,
)
from tests.support.recipe_check import RecipeError, compose_file, run_command, run_recipe, services

RECIPES, INLINE = all_printed()


def test_the_search_finds_the_recipes_users_follow() -> None:
    """The extraction itself: the recipes this issue is about are among those found."""
    found = {" ".join(c.argv) for r in RECIPES for c in r.commands}
    for expected in (
        "docker compose up --build",
        "docker compose --profile lab run --rm servotune-lab servotune users add alice "
        "--role admin",
        "docker compose --profile nats-lab run --rm servotune-hub servotune users add alice "
        "--role admin --data-dir /data/hub",
        "servotune users add alice --role admin",
    ):
        assert expected in found, expected
    wheres = {r.where.split(":")[0] for r in RECIPES}
    assert {"README.md", "docker-compose.yml", "docs/lab.md", "docs/remote-lab.md"} <= wheres
    assert any(c.argv[:2] == ["servotune", "bench"] for c in INLINE)
    assert len(RECIPES) >= 15


@pytest.mark.parametrize("recipe", RECIPES, ids=[r.where for r in RECIPES])
def test_each_printed_recipe_works_as_printed(recipe: Recipe) -> None:
    run_recipe(recipe)


@pytest.mark.parametrize("command", INLINE, ids=[c.where for c in INLINE])
def test_each_command_named_in_prose_parses(command: Printed) -> None:
    run_command(command)


def test_each_service_of_the_image_runs_a_command_the_cli_accepts() -> None:
    """docker-compose.yml's servotune services (and the image's CMD), as their container
    would start them; the demo's local mode on 0.0.0.0 passes the bind rule only with
    the loopback statement and a loopback-only publish."""
    from tests.support.recipe_check import check_bind_rule, image_environment, service_server_args

    checked = []
    for name, service in services(compose_file()).items():
        if not service.servotune_image or service.command()[:1] != ["servotune"]:
            continue
        with image_environment():
            args = service_server_args(service, "docker-compose.yml")
        check_bind_rule(args, service.environment(), service.spec.get("ports", []), name)
        checked.append(name)
    assert {"servotune-demo", "servotune-lab", "servotune-hub", "rig-1", "rig-2"} <= set(checked)


# --- the checks can fail: recipes once printed broken, and other wrong ones ------------


def _recipe(*lines: str, where: str = "example.md:1") -> Recipe:
    commands = [c for line in lines if (c := split_command(line, where)) is not None]
    return Recipe(where, commands)


@pytest.mark.parametrize(
    ("lines", "reason"),
    [
        # The hub's accounts must go where the hub reads them (/data/hub in the image).
        (
            [
                "servotune bus-accounts --leaf --rig rig-1 --rig rig-2 --viewer wall "
                "--out lab/nats/secrets",
                "docker compose --profile nats-lab run --rm servotune-hub servotune users "
                "add alice --role admin",
            ],
            "reads /data/hub/auth.db",
        ),
        # The old remote-lab recipe against a profile that needs the bus's secrets.
        (["docker compose --profile nats-lab up -d"], "does not exist and no earlier step"),
        (["servotune users add alice --role admin --data-dir"], "expected one argument"),
        (["servotune users add alice --role admin --admin"], "unrecognized arguments: --admin"),
        (["docker compose --profile remote up -d"], "no profile 'remote'"),
        (["docker compose --profile lab run --rm servotune servotune users list"], "no service"),
        # The image's local mode published on the LAN: refused by the bind rule.
        (["docker run --rm -p 8000:8000 servotune:demo"], "refusing local mode"),
        (
            ["docker run --rm -p 8000:8000 -e SERVOTUNE_LOOPBACK_PUBLISHED=1 servotune:demo"],
            "publishes 8000:8000",
        ),
    ],
)
def test_a_wrong_recipe_fails(lines: list[str], reason: str) -> None:
    with pytest.raises(RecipeError, match=reason.replace("(", r"\(")):
        run_recipe(_recipe(*lines))


def test_a_loopback_docker_run_of_the_image_passes() -> None:
    run_recipe(
        _recipe(
            "docker run --rm -p 127.0.0.1:8000:8000 -e SERVOTUNE_LOOPBACK_PUBLISHED=1 "
            "servotune:demo"
        )
    )


def test_markdown_blocks_inline_spans_and_comments_are_found() -> None:
    """The extractor on a markdown file and on the compose file's comments."""
    doc = ROOT / "docs" / "lab.md"
    recipes, spans = markdown(doc)
    assert any(c.argv[:2] == ["servotune", "hub"] for r in recipes for c in r.commands)
    assert all(c.inline for c in spans)
    compose_recipes = comments(ROOT / "docker-compose.yml")
    continued = [c for r in compose_recipes for c in r.commands if "--data-dir" in c.argv]
    assert continued, "a command continued on the next comment line is joined"
