"""The Dask scheduler a render run may use: its address checked without connecting, and the
connection, each one line on failure. Apart from the dispatcher so that the render options
(allo_usd.run.options) can check a --scheduler address without importing the dispatcher."""

from __future__ import annotations

from allo_usd.core.errors import AlloError
from allo_usd.core.timefmt import seconds_text

SCHEDULER_CONNECT_S = 5.0   # how long connecting to a --scheduler may take (distributed's default: 30 s)
SCHEDULER_SCHEMES = ("tcp", "tls", "ws", "wss")
# the fix a malformed --scheduler address is told (the render options check it first, connect_scheduler again)
SCHEDULER_FIX = ("fix: give the address `dask scheduler` prints, e.g. --scheduler tcp://HOST:8786, or leave it out "
                 "for a local pool")


def load_distributed() -> None:
    """Import Dask's distributed (and its comm registry) with Ctrl-C held (core.interrupts): a large
    import whose dependencies try optional modules under broad excepts, where a Ctrl-C could be
    swallowed or come out as another error."""
    from allo_usd.core.interrupts import import_held

    import_held("distributed")
    import_held("distributed.comm.registry")


def scheduler_problem(address) -> str | None:
    """Why `address` is not a Dask scheduler address one can connect to from another process, or
    None: SCHEME://HOST:PORT (tcp, tls, ws or wss; a bare HOST:PORT is tcp) with a port 1-65535, as
    distributed parses it. Checked before anything renders, without connecting."""
    load_distributed()
    from distributed.comm import get_address_host_port, parse_address
    from distributed.comm.registry import get_backend

    shown = str(address)[:200]
    try:
        scheme, _ = parse_address(str(address))
        if scheme not in SCHEDULER_SCHEMES:
            return f"{shown!r} is not a {', '.join(SCHEDULER_SCHEMES)} address"
        get_backend(scheme)
        host, port = get_address_host_port(str(address))
    except (ValueError, TypeError) as exc:
        return f"{shown!r} is not a scheduler address ({exc})"
    if not host or not 1 <= int(port) <= 65535:
        return f"{shown!r} has no host or a port outside 1-65535"
    return None


def connect_scheduler(address):
    """A distributed Client of the scheduler at `address` (an address, or a cluster object such as a
    LocalCluster), or an AlloError in one line: a malformed address at once (scheduler_problem), one
    that does not answer as a Dask scheduler within SCHEDULER_CONNECT_S (refused, unroutable, or
    something else listening there: distributed then reads garbage and may raise MemoryError)."""
    load_distributed()
    from distributed import Client

    why = scheduler_problem(address) if isinstance(address, str) else None   # else a cluster object
    if why:
        raise AlloError(f"--scheduler {why}; {SCHEDULER_FIX}")
    try:
        return Client(address, timeout=SCHEDULER_CONNECT_S)
    except Exception as exc:  # noqa: BLE001 - OSError (refused, timed out), or garbage read from a non-Dask server
        raise AlloError(f"--scheduler {str(address)[:200]}: no Dask scheduler answered within "
                        f"{seconds_text(SCHEDULER_CONNECT_S)} ({type(exc).__name__}: {str(exc)[:200]}); fix: start "
                        "one there (`dask scheduler`) and its workers, or check the address") from None
