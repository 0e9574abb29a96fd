"""The ``servotune`` command: demo, serve, hub, sim, perf (also ``bench``), users, tokens."""

from __future__ import annotations

import argparse
import logging
import os
import stat
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from servotune import __version__
from servotune.auth.cli import (
    add_account_commands,
    add_security_arguments,
    security_config_from_args,
)
from servotune.config import (
    ConfigError,
    LinkRulesSource,
    LinkSpec,
    load_config_file,
    parse_link_spec,
)
from servotune.storage import default_data_dir

if TYPE_CHECKING:
    from servotune.bus.connection import BusSettings


def _addresses(text: str) -> list[int]:
    """``--addresses 0,1``, parsed only: the device's range is checked once the device
    is known (``_address_problem``)."""
    try:
        return [int(a) for a in text.split(",") if a.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"addresses must be like 0,1 (got {text!r})") from None


def _address_problem(args: argparse.Namespace, devices: LinkRulesSource) -> str | None:
    """What is wrong with ``args.addresses`` for ``args.device`` (its link rules'
    ``address_range``), as argparse words it; None when nothing is."""
    values = getattr(args, "addresses", None)
    if values is None or args.device not in devices.names():
        return None  # no addresses here, or not a device (``servotune perf demo``)
    low, high = devices.link_rules(args.device).address_range
    if not values or any(not low <= a <= high for a in values) or len(set(values)) != len(values):
        return f"argument --addresses: addresses must be distinct numbers {low}..{high}"
    return None


# Seconds uvicorn waits for open requests at shutdown before it cancels them.
GRACEFUL_SHUTDOWN_S = 3


# The operator's statement that a container's port is published on the host's loopback
# only (docker -p 127.0.0.1:8000:8000): set by docker-compose.yml's demo service.
LOOPBACK_PUBLISHED_ENV = "SERVOTUNE_LOOPBACK_PUBLISHED"


def loopback_published(args: argparse.Namespace, environ: dict[str, str] | None = None) -> bool:
    """Whether ``--loopback-published`` or ``SERVOTUNE_LOOPBACK_PUBLISHED=1`` was given."""
    env = os.environ if environ is None else environ
    return bool(args.loopback_published) or env.get(LOOPBACK_PUBLISHED_ENV, "") == "1"


def local_bind_refusal(*, exposed: bool, host: str, published_on_loopback: bool) -> str | None:
    """Why the server must not start as configured (None: it may).

    Local mode has no login: on a non-loopback bind anyone who reaches the port could
    move the motors. Inside a container the server must bind 0.0.0.0, and only the
    operator knows whether the port is then published on the host's loopback only, so
    local mode there needs that said explicitly.
    """
    from servotune.auth.security import is_loopback

    if exposed or is_loopback(host) or published_on_loopback:
        return None
    return (
        f"refusing local mode (no login) on {host}: anyone who can reach that address "
        "could move the motors. Give accounts and TLS or a proxy for exposed mode "
        "(docs/remote-lab.md), bind 127.0.0.1, or, in a container whose port is "
        "published on the host's loopback only (docker run -p 127.0.0.1:8000:8000), "
        f"say so with {LOOPBACK_PUBLISHED_ENV}=1 or --loopback-published"
    )


def _add_bind_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--loopback-published",
        action="store_true",
        help="local mode on a non-loopback bind (a container's 0.0.0.0) is refused unless "
        "this says the port is published on the host's loopback only (also "
        f"{LOOPBACK_PUBLISHED_ENV}=1)",
    )


def _run_server(
    app_config: object, host: str, port: int, *, published_on_loopback: bool = False
) -> None:
    import uvicorn

    from servotune.api.app import AppConfig, create_app
    from servotune.api.ws import WS_MAX_MESSAGE_BYTES
    from servotune.auth.security import SecurityConfigError

    assert isinstance(app_config, AppConfig)
    security = app_config.security
    refusal = local_bind_refusal(
        exposed=security.exposed, host=host, published_on_loopback=published_on_loopback
    )
    if refusal is not None:
        print(f"servotune: {refusal}", file=sys.stderr)
        raise SystemExit(2)
    try:
        app = create_app(app_config)
    except SecurityConfigError as exc:
        print(f"servotune: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    scheme = "https" if security.tls else "http"
    mode = "exposed: login required" if security.exposed else "local"
    print(f"servotune {__version__}: {scheme}://{host}:{port}  ({mode})", flush=True)
    # proxy_headers off: forwarded headers are honoured by servotune.auth.middleware,
    # from the --proxy address only (uvicorn would trust any loopback peer).
    uvicorn.run(
        app,
        host=host,
        port=port,
        log_level="warning",
        proxy_headers=False,
        ssl_certfile=security.tls_cert,
        ssl_keyfile=security.tls_key,
        # uvicorn refuses bigger websocket frames (1009) before buffering them.
        ws_max_size=WS_MAX_MESSAGE_BYTES,
        # At shutdown uvicorn waits for open requests before the lifespan's STOP of
        # every axis: logins queued for the hashing workers (a flood) must not hold it.
        timeout_graceful_shutdown=GRACEFUL_SHUTDOWN_S,
    )


def _bus_settings(args: argparse.Namespace, *, hub: bool) -> BusSettings | None:
    """The bus options as ``BusSettings`` (None without ``--bus``); SystemExit(2) on bad
    ones. The credentials are a file name here: the file is read when connecting."""
    from servotune.bus.connection import BusSettings
    from servotune.bus.subjects import check_token

    if not args.bus:
        if not hub and args.rig:
            print("servotune serve: --rig needs --bus URL", file=sys.stderr)
            raise SystemExit(2)
        return None
    credentials = args.bus_credentials
    if credentials is not None and not credentials.is_file():
        print(f"servotune: --bus-credentials: no file {credentials}", file=sys.stderr)
        raise SystemExit(2)
    if credentials is not None:
        _check_credentials_readable(credentials, hub=hub)
    try:
        if hub:
            return BusSettings(
                url=args.bus, hub=check_token("--name", args.name), credentials=credentials
            )
        if not args.rig:
            print("servotune serve: --bus needs --rig NAME (this rig's name)", file=sys.stderr)
            raise SystemExit(2)
        return BusSettings(
            url=args.bus,
            rig=check_token("--rig", args.rig),
            credentials=credentials,
            leaf=args.bus_leaf,
        )
    except ValueError as exc:
        print(f"servotune: {exc}", file=sys.stderr)
        raise SystemExit(2) from None


def _check_credentials_readable(path: Path, *, hub: bool) -> None:
    """SystemExit(2) naming this process's uid when a credential file cannot be read
    (a container reads its secrets as the image's user, uid 1000: files written 0600 by
    another user are unreadable there)."""
    from servotune.bus.connection import role_credentials

    paths = [path]
    if hub:  # the view and STOP users' files next to the hub's, where present
        paths += [role_credentials(path, "view"), role_credentials(path, "stop")]
    for candidate in paths:
        if candidate != path and not candidate.exists():
            continue
        try:
            with candidate.open("rb"):
                pass
        except OSError as exc:
            uid = os.getuid()
            try:
                info = candidate.stat()
                owner = f"; it belongs to uid {info.st_uid}, mode {stat.filemode(info.st_mode)}"
            except OSError:
                owner = ""
            print(
                f"servotune: --bus-credentials: cannot read {candidate} as uid {uid} "
                f"({exc.strerror or exc}{owner}). Make it readable by uid {uid}: for "
                "docker-compose.yml's lab, chown -R 1000 lab/nats/secrets (docs/lab.md)",
                file=sys.stderr,
            )
            raise SystemExit(2) from None


def _add_bus_arguments(parser: argparse.ArgumentParser, *, hub: bool) -> None:
    group = parser.add_argument_group("lab bus (NATS, docs/lab.md)")
    group.add_argument(
        "--bus",
        default=None,
        required=hub,
        metavar="URL",
        help="nats-server of the lab, e.g. nats://lab-nats:4222",
    )
    group.add_argument(
        "--bus-credentials",
        type=Path,
        default=None,
        metavar="FILE",
        help="a .creds file, or a file with the user name on line 1 and the password on "
        "line 2 (never on the command line)",
    )
    if hub:
        group.add_argument("--name", default="lab", help="this hub's name on the bus")
    else:
        group.add_argument("--rig", default=None, metavar="NAME", help="this rig's name")
        group.add_argument(
            "--bus-leaf",
            action="store_true",
            help="--bus is this rig's own nats-server, a leaf node of the lab's with "
            "JetStream in domain NAME (its runs are kept there; docs/lab.md)",
        )


def cmd_bus_accounts(args: argparse.Namespace) -> int:
    """Write the lab's nats-server accounts and a credentials file per user."""
    from servotune.bus.accounts import lab_accounts, write_lab_accounts

    try:
        accounts = lab_accounts(args.hub, args.rig, args.viewer, leaf=args.leaf)
    except ValueError as exc:
        print(f"servotune bus-accounts: {exc}", file=sys.stderr)
        return 2
    for path in write_lab_accounts(args.out, accounts):
        print(f"wrote {path}")  # names only: the passwords stay in the files
    if args.leaf:
        from servotune.bus.accounts import write_private
        from servotune.bus.leaf import leaf_node_conf

        for rig in args.rig:
            path = args.out / f"{rig}.leaf.conf"
            text = leaf_node_conf(
                rig,
                port=4222,
                store_dir=args.leaf_store,
                lab_leaf_url=args.leaf_url,
                credentials_file=args.out / f"{rig}.cred",
            )
            write_private(path, text)
            print(f"wrote {path}")
    print(
        f"The files are readable by their owner only (uid {os.getuid()}, mode 0600). The "
        "servotune image runs as uid 1000: for docker-compose.yml's lab, chown -R 1000 "
        f"{args.out} (docs/lab.md)"
    )
    return 0


# Under the default data directory, each server command's own (``--data-dir`` replaces
# it); ``servotune users``/``tokens`` must be given the same directory.
_DATA_SUBDIR = {"demo": "demo", "serve": "", "hub": "hub"}


def server_data_dir(args: argparse.Namespace) -> Path:
    """The data directory ``demo``, ``serve`` or ``hub`` keeps its stores in."""
    explicit: Path | None = args.data_dir
    return explicit or default_data_dir() / _DATA_SUBDIR[args.command]


def cmd_demo(args: argparse.Namespace) -> int:
    from servotune.api.app import AppConfig
    from servotune.demo import demo_simulators, demo_state_dir
    from servotune.devices import default_registry

    devices = default_registry()
    data_dir = server_data_dir(args)
    with demo_state_dir(data_dir) as (state_dir, problem):
        if problem is not None:
            logging.getLogger(__name__).warning(
                "%s: the simulated EEPROMs and flash are kept in %s for this run only",
                problem,
                state_dir,
            )
        config = AppConfig(
            data_dir=data_dir,
            autopilot=not args.no_autopilot,
            simulators=demo_simulators(
                data_dir, state_dir, ethercat_wire=args.ethercat_wire, devices=devices
            ),
            devices=devices,
            security=security_config_from_args(args, args.host),
        )
        _run_server(config, args.host, args.port, published_on_loopback=loopback_published(args))
    return 0


def cmd_serve(args: argparse.Namespace) -> int:
    from servotune.api.app import AppConfig
    from servotune.devices import default_registry

    devices = default_registry()
    links: list[LinkSpec] = []
    host, port = args.host, args.port
    try:
        if args.config:
            file_config = load_config_file(Path(args.config), devices)
            links.extend(file_config.links)
            host = args.host if args.host != "127.0.0.1" else (file_config.host or host)
            port = args.port if args.port != 8000 else (file_config.port or port)
        links.extend(parse_link_spec(spec, devices) for spec in args.link)
    except ConfigError as exc:
        print(f"servotune serve: {exc}", file=sys.stderr)
        return 2
    if not links:
        print(
            "servotune serve: give at least one --link (e.g. "
            "'slap2:/dev/ttyUSB0?addresses=0,1&baud=19200&lines=512') or --config FILE",
            file=sys.stderr,
        )
        return 2
    bus = _bus_settings(args, hub=False)
    config = AppConfig(
        links=links,
        devices=devices,
        data_dir=server_data_dir(args),
        security=security_config_from_args(args, host),
        bus=bus,
    )
    _run_server(config, host, port, published_on_loopback=loopback_published(args))
    return 0


def cmd_hub(args: argparse.Namespace) -> int:
    """The lab's central dashboard: every axis of every rig on the bus."""
    from servotune.api.app import AppConfig

    bus = _bus_settings(args, hub=True)
    config = AppConfig(
        links=[],
        data_dir=server_data_dir(args),
        security=security_config_from_args(args, args.host),
        bus=bus,
        twin=False,
    )
    _run_server(config, args.host, args.port, published_on_loopback=loopback_published(args))
    return 0


def cmd_sim(args: argparse.Namespace) -> int:
    from servotune.devices import default_registry
    from servotune.registry import SimArgs

    simulator = default_registry().get(args.device).simulator
    assert simulator is not None  # argparse's choices are the simulated devices
    return simulator.serve(
        SimArgs(
            addresses=tuple(args.addresses),
            baud=args.baud,
            state_dir=args.state_dir,
            link=args.link,
            socket=args.socket,
            ifname=args.ifname,
            control=args.control,
            product=args.product,
            realtime=not args.no_rt,
        )
    )


def _hex_int(text: str) -> int:
    try:
        return int(text, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None


def cmd_perf(args: argparse.Namespace) -> int:
    if args.device == "demo":
        from servotune.perf.demo import run_demo_bench

        return run_demo_bench(
            seconds=args.seconds if args.seconds is not None else 30.0,
            hog=args.hog,
            port=args.port,
            url=args.url,
            pid=args.pid,
        )
    from servotune.perf.link_rate import run_bench

    return run_bench(
        device=args.device,
        baud=args.baud,
        addresses=args.addresses,
        duration_s=args.seconds if args.seconds is not None else 5.0,
    )


def build_parser() -> argparse.ArgumentParser:
    from servotune.devices import default_registry

    devices = default_registry()
    simulated = [entry.name for entry in devices.simulated()]
    on_pty = devices.simulated(pty=True)
    default_bauds = ", ".join(f"{e.link_rules.default_baud} ({e.name})" for e in on_pty)
    parser = argparse.ArgumentParser(prog="servotune", description=__doc__)
    parser.add_argument("--version", action="version", version=__version__)
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug output")
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="dashboard with simulated devices")
    demo.add_argument("--host", default="127.0.0.1")
    demo.add_argument("--port", type=int, default=8000)
    demo.add_argument("--no-autopilot", action="store_true", help="no automatic demo moves")
    demo.add_argument("--data-dir", type=Path, default=None)
    demo.add_argument(
        "--ethercat-wire",
        action="store_true",
        help="the EP7047 as a real EtherCAT slave on a veth pair, driven by pysoem (root; "
        "default: behind the master seam)",
    )
    add_security_arguments(demo)
    _add_bind_arguments(demo)
    demo.set_defaults(func=cmd_demo)

    serve = sub.add_parser("serve", help="dashboard for real devices")
    serve.add_argument(
        "--link",
        action="append",
        default=[],
        help="device:path?options, e.g. slap2:/dev/ttyUSB0?addresses=0,1&baud=19200&lines=512",
    )
    serve.add_argument("--config", help="TOML file with [[link]] tables")
    serve.add_argument("--host", default="127.0.0.1")
    serve.add_argument("--port", type=int, default=8000)
    serve.add_argument("--data-dir", type=Path, default=None)
    add_security_arguments(serve)
    _add_bind_arguments(serve)
    _add_bus_arguments(serve, hub=False)
    serve.set_defaults(func=cmd_serve)

    hub = sub.add_parser("hub", help="the lab's dashboard: every rig on the NATS bus")
    hub.add_argument("--host", default="127.0.0.1")
    hub.add_argument("--port", type=int, default=8000)
    hub.add_argument("--data-dir", type=Path, default=None)
    add_security_arguments(hub)
    _add_bind_arguments(hub)
    _add_bus_arguments(hub, hub=True)
    hub.set_defaults(func=cmd_hub)

    accounts = sub.add_parser(
        "bus-accounts",
        help="write the lab nats-server's users and permissions and their credential files",
    )
    accounts.add_argument("--hub", default="hub", help="the hub's user name")
    accounts.add_argument("--rig", action="append", default=[], help="a rig (repeatable)")
    accounts.add_argument("--viewer", action="append", default=[], help="a read-only user")
    accounts.add_argument("--out", type=Path, required=True, help="directory to write to")
    accounts.add_argument(
        "--leaf",
        action="store_true",
        help="the rigs run their own nats-server as leaf nodes (docs/lab.md): also write "
        "<rig>.leaf.conf, the configuration of each rig's nats-server",
    )
    accounts.add_argument(
        "--leaf-url",
        default="nats-leaf://nats:7422",
        help="--leaf: the lab server's leaf node listener as the rigs reach it",
    )
    accounts.add_argument(
        "--leaf-store",
        type=Path,
        default=Path("/data/nats"),
        help="--leaf: JetStream directory on the rig PC",
    )
    accounts.set_defaults(func=cmd_bus_accounts)

    sim = sub.add_parser(
        "sim",
        help="serve a simulated device on a new pseudo-terminal (slap2, z1100), a Unix "
        "socket (ep7047 --socket: link spec ep7047:sim:PATH) or a network interface "
        "(ep7047 --ifname: a real EtherCAT slave)",
    )
    sim.add_argument("device", choices=simulated)
    sim.add_argument("--addresses", type=_addresses, default=[0, 1], help="SLAP2 modules")
    sim.add_argument("--baud", type=int, default=None, help=default_bauds)
    sim.add_argument("--state-dir", type=Path, default=None, help="where EEPROM files live")
    sim.add_argument("--link", default=None, help="also create this symlink to the pty")
    sim.add_argument("--socket", default=None, help="ep7047: the Unix socket to serve on")
    sim.add_argument(
        "--ifname",
        default=None,
        help="ep7047: a real EtherCAT slave on this network interface (raw socket; "
        "docs/ep7047-wire.md); link spec ep7047:<the master's interface>",
    )
    sim.add_argument(
        "--control", default=None, help="ep7047 --ifname: a Unix socket for fault injection"
    )
    sim.add_argument(
        "--product",
        type=_hex_int,
        default=None,
        help="ep7047 --ifname: another product code in the SII (identity tests)",
    )
    sim.add_argument("--no-rt", action="store_true", help="ep7047 --ifname: no real-time priority")
    sim.set_defaults(func=cmd_sim, subparser=sim)

    # ``perf`` is the command's name; ``bench`` stays for the scripts that call it so.
    perf_help = (
        "telemetry rate against the wire limit (one device, or the whole demo: "
        "CPU per process and every link's rate)"
    )
    for name, help_text in (("perf", perf_help), ("bench", "the same as perf")):
        perf = sub.add_parser(name, help=help_text)
        perf.add_argument("device", choices=[*(e.name for e in on_pty), "demo"])
        perf.add_argument("--baud", type=int, default=None, help=default_bauds)
        perf.add_argument("--addresses", type=_addresses, default=[0])
        perf.add_argument("--seconds", type=float, default=None, help="5 (device), 30 (demo)")
        perf.add_argument(
            "--hog",
            choices=["off", "on", "both"],
            default="both",
            help="demo: measure without, with, or without and then with a CPU hog on every core",
        )
        perf.add_argument("--port", type=int, default=None, help="demo: port (default: a free one)")
        perf.add_argument("--url", default=None, help="demo: measure this running server instead")
        perf.add_argument(
            "--pid", type=int, default=None, help="demo: process id of --url's server"
        )
        perf.set_defaults(func=cmd_perf, subparser=perf)
    add_account_commands(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    from servotune.devices import default_registry

    args = build_parser().parse_args(argv)
    problem = _address_problem(args, default_registry())
    if problem is not None:
        args.subparser.error(problem)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    result: int = args.func(args)
    return result


if __name__ == "__main__":
    sys.exit(main())
