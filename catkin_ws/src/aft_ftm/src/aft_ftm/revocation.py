"""One revocation for both security layers (issue 16): a party's SEC certificate (the CA node's
revocations file, ``<keys_dir>/revoked.yaml``) and its TLS certificates (the TLS authority's signed
list, ``ca.tls.crl``, copied into each party directory the nodes read) are revoked by one command,
``rosrun aft_ftm revoke``. Before, an operator revoking a stolen key in one layer left it valid in
the other (review of session 41).

Everything is checked before anything is written: no layer named, a party neither layer knows, a
malformed revocations file, a missing TLS authority or copy directory raise ConfigError naming the
problem, and nothing changes. A party one layer does not know is revoked in the other, and the
result says so. Plain Python, no ROS.
"""
import os

import yaml

from . import sec_policy, tls
from .errors import ConfigError

SEC_FILE = 'revoked.yaml'


def _sec_known(keys_dir, party):
    return os.path.isfile(os.path.join(keys_dir, party + '.pub'))


def _tls_known(tls_dir, party):
    try:
        tls.serial_of(tls_dir, party)
        return True
    except ConfigError:
        return party in tls.issued_serials(tls_dir)


def plan(parties, sec_dir=None, tls_dir=None, copy_to=()):
    """What revoke() will do: {'sec': [parties], 'tls': [parties], 'unknown': {party: layers}}.
    ConfigError if it cannot be done as asked (nothing is changed by a plan)."""
    if not parties:
        raise ConfigError('no party named')
    if not sec_dir and not tls_dir:
        raise ConfigError('name the SEC keys directory (--sec) or the TLS authority directory (--tls), or both')
    if copy_to and not tls_dir:
        raise ConfigError('--copy-to distributes the TLS revocation list: name the TLS authority (--tls)')
    for party in parties:
        if not party or not all(c.isalnum() or c in '_-' for c in party):
            raise ConfigError('%r is not a party name (letters, digits, - or _)' % (party,))
    done = {'sec': [], 'tls': [], 'unknown': {}}
    if sec_dir:
        if not os.path.isdir(sec_dir):
            raise ConfigError('SEC keys directory %s does not exist' % sec_dir)
        sec_policy.load_revocations(os.path.join(sec_dir, SEC_FILE))   # malformed: said before any change
    if tls_dir:
        if not os.path.isfile(os.path.join(tls_dir, 'ca.tls.key')):
            raise ConfigError('%s is not a TLS authority directory (no ca.tls.key: tls_keygen makes it)' % tls_dir)
        tls.issued_serials(tls_dir)   # a corrupt record: said before any change
        for directory in copy_to:
            if not os.path.isdir(directory):
                raise ConfigError('--copy-to %s: no such directory' % directory)
    for party in parties:
        missing = []
        for layer, directory, known in (('sec', sec_dir, _sec_known), ('tls', tls_dir, _tls_known)):
            if directory and known(directory, party):
                done[layer].append(party)
            elif directory:
                missing.append(layer.upper())
        if missing:
            done['unknown'][party] = missing
    nowhere = [p for p, layers in done['unknown'].items() if len(layers) == bool(sec_dir) + bool(tls_dir)]
    if nowhere:
        raise ConfigError('unknown to %s: %s (no SEC public key, no TLS certificate issued)' % (
            ' and '.join(l for l, d in (('SEC', sec_dir), ('TLS', tls_dir)) if d), ', '.join(nowhere)))
    return done


def revoke(parties, sec_dir=None, tls_dir=None, copy_to=()):
    """Revoke parties in both layers (module docstring). Returns lines saying what was done."""
    parties = list(dict.fromkeys(parties))
    todo = plan(parties, sec_dir, tls_dir, copy_to)
    said = []
    if todo['sec']:
        path = os.path.join(sec_dir, SEC_FILE)
        barred = sec_policy.load_revocations(path)
        barred += [p for p in todo['sec'] if p not in barred]
        tls.write_file(path, yaml.safe_dump({'revoked': barred}, default_flow_style=False).encode(), 0o644)
        said.append('SEC: %s revoked in %s (the CA refuses the certificates within its status period, 0.5 s)'
                    % (', '.join(todo['sec']), path))
    if todo['tls']:
        path, number = tls.revoke(tls_dir, todo['tls'])
        with open(path, 'rb') as f:
            crl = f.read()
        for directory in copy_to:
            tls.write_file(os.path.join(directory, tls.CRL), crl, 0o644)
        said.append('TLS: %s revoked, list number %d in %s%s' % (
            ', '.join(todo['tls']), number, path,
            '; copied into %s (their nodes cut the revoked connections within a second)' % ', '.join(copy_to)
            if copy_to else '; copy it into every party\'s TLS directory'))
    for party, layers in sorted(todo['unknown'].items()):
        said.append('%s: not a %s party, not revoked there' % (party, ' or '.join(layers)))
    return said
