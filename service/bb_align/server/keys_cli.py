"""``bb-align keys``: the fleet authority, vehicle credentials and the signed revocation list.

Every command can be run again: ``init`` keeps an existing authority, ``issue`` an existing credential (``--force``
replaces either), and both print what they keep. ``issue`` and ``env`` print the settings of a credential as
shell (``eval "$(bb-align keys env DIR ego)"``); when they fail, stdout gets ``false`` (the message goes to stderr),
so ``eval`` fails too instead of silently setting nothing. ``revoke`` names a key by its fingerprint, a certificate
or a vehicle id, from the authority's register of issued certificates (``DIR/issued/``): no private file needed.
"""

from __future__ import annotations

import shlex
import sys
import time
from pathlib import Path

import typer

keys_app = typer.Typer(
    help="Fleet authority and vehicle credentials (Ed25519, docs/security.md).",
    no_args_is_help=True,
    rich_markup_mode=None,
)


def _fail(command: str, problem: str, shell: bool = False) -> typer.Exit:
    """One line on stderr, exit 2; for a command whose output is eval'ed, ``false`` on stdout so eval fails too."""
    typer.secho(f"bb-align: keys {command}: {problem}", err=True, fg="red")
    if shell and not sys.stdout.isatty():
        typer.echo("false")
    return typer.Exit(2)


def _vehicle_id(command: str, vehicle_id: str) -> str:
    import re

    from bb_align.protocol import VEHICLE_ID_PATTERN

    if not re.match(VEHICLE_ID_PATTERN, vehicle_id):
        raise _fail(command, f"{vehicle_id!r} is not a vehicle id ({VEHICLE_ID_PATTERN})", shell=True)
    return vehicle_id


def _check_kept(command: str, directory: Path, cred) -> None:
    """A credential kept must still be one the authority in ``directory`` vouches for (not expired, not revoked,
    not from an authority replaced since): otherwise its settings would make a service that refuses to start."""
    from bb_align.protocol import IdentityError, TrustStore

    try:
        store = TrustStore.load(directory / "ca.pub")
        if (directory / "revoked.json").exists():
            store.use_revocations(directory / "revoked.json")
        store.certificate(cred.certificate_bytes)
    except IdentityError as e:
        raise _fail(
            command,
            f"{directory / (cred.vehicle_id + '.cred')} is not valid under {directory / 'ca.pub'} ({e.detail}): "
            f"bb-align keys issue {directory} {cred.vehicle_id} --force",
            shell=True,
        ) from None


def _exports(directory: Path, vehicle_id: str, cred: Path) -> list[str]:
    """The settings that make a service use ``cred`` as its own identity, as shell."""
    lines = [
        f"export BBALIGN_EGO_ID={shlex.quote(vehicle_id)}",
        f"export BBALIGN_AUTH__CA_CERT={shlex.quote(str((directory / 'ca.pub').resolve()))}",
        f"export BBALIGN_AUTH__CREDENTIAL={shlex.quote(str(cred.resolve()))}",
    ]
    revoked = directory / "revoked.json"
    if revoked.exists():
        lines.append(f"export BBALIGN_AUTH__REVOCATIONS={shlex.quote(str(revoked.resolve()))}")
    return lines


@keys_app.command("init")
def keys_init(
    directory: Path = typer.Argument(..., help="where ca.pub and ca.key go"),
    name: str = typer.Option("bb-align-fleet-ca", help="the authority's name (certificates name their issuer)"),
    force: bool = typer.Option(False, "--force", help="replace an existing authority (every credential with it)"),
) -> None:
    """Make a fleet authority: DIR/ca.pub (give it to every service and car) and DIR/ca.key (keep it offline).
    An existing authority is kept (run it again freely); --force replaces it."""
    from bb_align.protocol import FleetAuthority

    pub, key = directory / "ca.pub", directory / "ca.key"
    if key.exists() and not force:
        try:
            FleetAuthority.load(directory)
        except (OSError, ValueError, KeyError) as e:
            raise _fail("init", f"{key}: {e}") from None
        typer.echo(f"# kept the authority in {directory} (--force replaces it)\n{pub}\n{key}")
        return
    try:
        pub, key = FleetAuthority.generate(name).save(directory)
    except OSError as e:
        raise _fail("init", f"{directory}: {e.strerror or e}") from None
    typer.echo(f"{pub} (trusted by services and cars)\n{key} (mode 0600: keep it offline)")


@keys_app.command("issue")
def keys_issue(
    directory: Path = typer.Argument(..., help="the authority's directory (bb-align keys init)"),
    vehicle_id: str = typer.Argument(..., help="the vehicle the credential is for"),
    days: float = typer.Option(365.0, min=0.001, help="validity, days"),
    force: bool = typer.Option(
        False, "--force", help="replace an existing credential of this vehicle (a new key: key rotation)"
    ),
) -> None:
    """Issue DIR/<VEHICLE_ID>.cred: a fresh Ed25519 key and its certificate (mode 0600; give it to that car only).
    An existing credential is kept (--force makes a new key). Prints, as shell, the settings that make a service
    use it as its own identity: ``eval "$(bb-align keys issue DIR ego)"; bb-align serve``."""
    from bb_align.protocol import Credential, FleetAuthority, fingerprint
    from bb_align.protocol.revocations import record_issued

    target = directory / f"{_vehicle_id('issue', vehicle_id)}.cred"
    try:
        if target.exists() and not force:
            cred = Credential.load(target)
            _check_kept("issue", directory, cred)
            typer.echo(
                f"# kept {target} (key {fingerprint(cred.certificate.public_key)[:16]}; --force makes a new key)"
            )
        else:
            cred = FleetAuthority.load(directory).issue(vehicle_id, days=days)
            cred.save(target)
            record_issued(directory, cred.certificate)
            typer.echo(f"# wrote {target} (key {fingerprint(cred.certificate.public_key)[:16]})")
    except FileNotFoundError as e:
        raise _fail("issue", f"{e.filename}: no such file (bb-align keys init {directory})", shell=True) from None
    except (OSError, ValueError, KeyError) as e:
        raise _fail("issue", str(e), shell=True) from None
    typer.echo(f"# for a service whose ego id is {vehicle_id!r}:")
    typer.echo("\n".join(_exports(directory, vehicle_id, target)))


@keys_app.command("env")
def keys_env(
    directory: Path = typer.Argument(..., help="the authority's directory (bb-align keys init)"),
    vehicle_id: str = typer.Argument(..., help="the vehicle whose credential the service uses as its own"),
) -> None:
    """Print, as shell, the settings of an existing credential: ``eval "$(bb-align keys env DIR ego)"``."""
    from bb_align.protocol import Credential

    target = directory / f"{_vehicle_id('env', vehicle_id)}.cred"
    try:
        cred = Credential.load(target)
    except FileNotFoundError:
        raise _fail(
            "env", f"{target}: no such credential (bb-align keys issue {directory} {vehicle_id})", True
        ) from None
    except (OSError, ValueError, KeyError) as e:
        raise _fail("env", f"{target}: {e}", shell=True) from None
    if cred.vehicle_id != vehicle_id:
        raise _fail("env", f"{target} is {cred.vehicle_id!r}'s credential, not {vehicle_id!r}'s", shell=True)
    try:
        _check_kept("env", directory, cred)
    except (OSError, ValueError, KeyError) as e:
        raise _fail("env", f"{directory / 'ca.pub'}: {e}", shell=True) from None
    typer.echo("\n".join(_exports(directory, vehicle_id, target)))


def _candidates(directory: Path) -> list:
    """Every certificate the authority knows of: its register, and (for credentials issued before the register
    existed) the credential files' own certificates."""
    from bb_align.protocol.revocations import issued_certificates, load_certificate

    found = {c.public_key: c for c in issued_certificates(directory)}
    for cred in sorted(directory.glob("*.cred")):
        try:
            cert = load_certificate(cred)
        except (OSError, ValueError, KeyError):
            continue
        found.setdefault(cert.public_key, cert)
    return list(found.values())


def _describe(cert, revoked) -> str:
    from bb_align.protocol import fingerprint

    state = "revoked" if revoked is not None and revoked.revokes(cert.public_key) else "valid"
    if state == "valid" and cert.not_after < time.time():
        state = "expired"
    issued = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(cert.not_before + 60))
    return f"{cert.vehicle_id}  {fingerprint(cert.public_key)}  issued {issued} UTC  {state}"


@keys_app.command("list")
def keys_list(
    directory: Path = typer.Argument(..., help="the authority's directory (bb-align keys init)"),
    vehicle_id: str | None = typer.Argument(None, help="only this vehicle's certificates"),
) -> None:
    """The certificates the authority issued: vehicle id, key fingerprint (what revoke --fingerprint takes), when,
    and whether valid, revoked or expired."""
    from bb_align.protocol.revocations import RevocationList

    try:
        revoked = RevocationList.load(directory / "revoked.json") if (directory / "revoked.json").exists() else None
        certs = [c for c in _candidates(directory) if vehicle_id in (None, c.vehicle_id)]
    except (OSError, ValueError, KeyError) as e:
        raise _fail("list", str(e)) from None
    for cert in sorted(certs, key=lambda c: (c.vehicle_id, c.not_before)):
        typer.echo(_describe(cert, revoked))


@keys_app.command("revoke")
def keys_revoke(
    directory: Path = typer.Argument(..., help="the authority's directory (bb-align keys init)"),
    vehicle_id: str | None = typer.Argument(
        None, help="the vehicle whose key is revoked (its only valid certificate; else name one)"
    ),
    fp: list[str] | None = typer.Option(
        None, "--fingerprint", metavar="FP", help="a key's fingerprint (bb-align keys list; 8+ hex digits of it)"
    ),
    cert_file: Path | None = typer.Option(
        None, "--cert", help="a .cert (DIR/issued/) or .cred file: its certificate's key (no private key read)"
    ),
    every: bool = typer.Option(False, "--all", help="every valid key of VEHICLE_ID"),
) -> None:
    """Revoke keys: add them to DIR/revoked.json, the list the authority signs (its version grows by one).
    Services with BBALIGN_AUTH__REVOCATIONS=DIR/revoked.json refuse them within seconds, and refuse an older list
    put back. Name the key by --fingerprint, --cert, or VEHICLE_ID alone when that vehicle has one valid key.
    To rotate a key: ``bb-align keys issue DIR car1 --force`` (a new key, same id), give the car its new
    credential, then revoke the old one with --fingerprint (``bb-align keys list DIR car1``)."""
    from bb_align.protocol import FleetAuthority
    from bb_align.protocol.revocations import RevocationList, load_certificate

    path = directory / "revoked.json"
    try:
        ca = FleetAuthority.load(directory)
        previous = RevocationList.load(path) if path.exists() else None
        known = _candidates(directory)
    except (OSError, ValueError, KeyError) as e:
        raise _fail("revoke", str(e)) from None
    chosen = _by_fingerprint(fp or [], known, vehicle_id)  # SHA-256 fingerprint -> vehicle id
    if cert_file is not None:
        try:
            cert = load_certificate(cert_file)
        except (OSError, ValueError, KeyError) as e:
            raise _fail("revoke", f"--cert {cert_file}: {e}") from None
        if cert.issuer != ca.name:
            raise _fail("revoke", f"--cert {cert_file}: issued by {cert.issuer!r}, not by {ca.name!r}")
        chosen[_digest(cert)] = cert.vehicle_id
    if vehicle_id is not None and any(v not in (vehicle_id, "?") for v in chosen.values()):
        raise _fail("revoke", f"the key named is {sorted(set(chosen.values()))}'s, not {vehicle_id!r}'s")
    if not chosen:
        chosen = _by_vehicle(directory, vehicle_id, known, previous, every)
    revoked = ca.revoke(chosen, previous)
    revoked.save(path)
    for digest, vid in chosen.items():
        typer.echo(f"# revoked {vid} key {digest.hex()}")
    typer.echo(f"# {path}: version {revoked.version}, {len(revoked.entries)} revoked; services need:")
    typer.echo(f"export BBALIGN_AUTH__REVOCATIONS={shlex.quote(str(path.resolve()))}")


def _digest(cert) -> bytes:
    from bb_align.protocol import fingerprint

    return bytes.fromhex(fingerprint(cert.public_key))


def _by_fingerprint(given: list[str], known: list, vehicle_id: str | None) -> dict[bytes, str]:
    """The keys named by --fingerprint: a unique prefix (8+ hex digits) of a certificate issued here, or a full
    fingerprint (a key this directory never recorded)."""
    from bb_align.protocol import fingerprint
    from bb_align.protocol.revocations import FINGERPRINT_HEX

    chosen = {}
    for fp in given:
        h = fp.lower()
        if not (8 <= len(h) <= FINGERPRINT_HEX and all(ch in "0123456789abcdef" for ch in h)):
            raise _fail("revoke", f"--fingerprint {fp!r}: 8 to {FINGERPRINT_HEX} hex digits (bb-align keys list)")
        hits = [c for c in known if fingerprint(c.public_key).startswith(h)]
        if len(hits) > 1:
            raise _fail("revoke", f"--fingerprint {fp}: {len(hits)} keys start with it; give more digits")
        if hits:
            chosen[_digest(hits[0])] = hits[0].vehicle_id
        elif len(h) == FINGERPRINT_HEX:
            chosen[bytes.fromhex(h)] = vehicle_id or "?"
        else:
            raise _fail("revoke", f"--fingerprint {fp}: no certificate issued here has it (bb-align keys list)")
    return chosen


def _by_vehicle(directory: Path, vehicle_id: str | None, known: list, previous, every: bool) -> dict[bytes, str]:
    """VEHICLE_ID alone: its one valid key (or, with --all, every one); never a guess between several."""
    from bb_align.protocol import fingerprint

    if vehicle_id is None:
        raise _fail("revoke", "name what to revoke: VEHICLE_ID, --fingerprint FP or --cert FILE")
    valid = [c for c in known if c.vehicle_id == vehicle_id and not (previous and previous.revokes(c.public_key))]
    if not valid:
        raise _fail("revoke", f"{vehicle_id!r} has no valid certificate issued in {directory} (bb-align keys list)")
    if len(valid) > 1 and not every:
        keys = ", ".join(fingerprint(c.public_key)[:16] for c in valid)
        raise _fail(
            "revoke", f"{vehicle_id!r} has {len(valid)} valid keys ({keys}): name one with --fingerprint, or --all"
        )
    return {_digest(c): c.vehicle_id for c in valid}
