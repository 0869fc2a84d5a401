"""One revocation for both security layers (issue 16): a party's SEC certificate (the CA node's
revocations file, ``<keys_dir>/revoked.yaml``) and its TLS certificates (the TLS authority's signed
list, ``ca.tls.crl``, copied into each party directory the nodes read) are revoked by one command,
``rosrun aft_ftm revoke``. Before, an operator revoking a stolen key in one layer left it valid in
the other (review of session 41).

Everything that can be checked is checked before anything is written (:func:`plan`): no layer
named, a party neither layer knows (or ``ca``), a malformed revocations file or revocation list, an
unusable TLS authority, a party without a current TLS certificate, a copy directory missing,
unwritable, of another CA or holding a newer list raise ConfigError naming the problem, and nothing
changes. A party one layer does not know is revoked in the other, and the result says so. What can
still fail once writing began (the disk) raises :class:`Incomplete`, saying what was done. Each
layer's files are written under a lock (``flock``), so that two revocations at once (this command,
``tls_keygen --revoke``) lose nothing. Plain Python, no ROS.
"""
import os

import yaml

from . import sec_policy, tls
from .errors import ConfigError

SEC_FILE = 'revoked.yaml'


class Incomplete(Exception):
    """Writing failed part way: ``done`` says what was written (each layer's step is whole)."""

    def __init__(self, done, error):
        Exception.__init__(self, '%s; done before it: %s' % (error, '; '.join(done) or 'nothing'))
        self.done = done


def _sec_known(keys_dir, party):
    return os.path.isfile(os.path.join(keys_dir, party + '.pub'))


def _tls_known(tls_dir, party):
    """Whether the authority has a current certificate of party (what tls.revoke needs); a party it
    once issued to but whose certificate is gone is said, not taken for unknown."""
    try:
        tls.serial_of(tls_dir, party)
        return True
    except ConfigError:
        if party in tls.issued_serials(tls_dir):
            raise ConfigError('TLS party %s: its certificates are recorded as issued, but its current one (%s) '
                              'cannot be read: revoke its serials with tls_keygen, or issue it again first'
                              % (party, os.path.join(tls_dir, party + '.tls.crt')))
        return False


def _held_list(tls_dir):
    """The authority's current revocation list, checked (a corrupt one: ConfigError)."""
    _, ca_cert = tls._authority(tls_dir)
    held = tls.Revocations(ca_cert.public_key())
    path = os.path.join(tls_dir, tls.CRL)
    if os.path.exists(path):
        with open(path, 'rb') as f:
            try:
                held.take(f.read())
            except ConfigError as e:
                raise ConfigError('the authority\'s revocation list %s: %s' % (path, e))
    return held


def _check_copy_dir(directory, tls_dir, next_number):
    if not os.path.isdir(directory):
        raise ConfigError('--copy-to %s: no such directory' % directory)
    if not os.access(directory, os.W_OK):
        raise ConfigError('--copy-to %s: not writable by this user' % directory)
    ca = os.path.join(directory, 'ca.tls.crt')
    try:
        with open(ca, 'rb') as f, open(os.path.join(tls_dir, 'ca.tls.crt'), 'rb') as g:
            same = f.read() == g.read()
    except OSError as e:
        raise ConfigError('--copy-to %s: not a party directory of this authority (%s)' % (directory, e))
    if not same:
        raise ConfigError('--copy-to %s: its CA certificate is another authority\'s: its nodes would refuse the list'
                          % directory)
    held = tls.held_number(directory)
    if held is not None and held >= next_number:
        raise ConfigError('--copy-to %s: its nodes took list number %d already; the new one would be %d, which '
                          'they refuse as a rollback' % (directory, held, next_number))


def plan(parties, sec_dir=None, tls_dir=None, copy_to=()):
    """What revoke() will do: {'sec': [parties], 'tls': [parties], 'unknown': {party: layers}}.
    ConfigError if it cannot be done as asked (a plan changes nothing)."""
    if not parties:
        raise ConfigError('no party named')
    if not sec_dir and not tls_dir:
        raise ConfigError('name the SEC keys directory (--sec) or the TLS authority directory (--tls), or both')
    if copy_to and not tls_dir:
        raise ConfigError('--copy-to distributes the TLS revocation list: name the TLS authority (--tls)')
    for party in parties:
        if not party or not all(c.isalnum() or c in '_-' for c in party):
            raise ConfigError('%r is not a party name (letters, digits, - or _)' % (party,))
        if party == 'ca':
            raise ConfigError('ca is the certification authority itself, not a party to revoke')
    done = {'sec': [], 'tls': [], 'unknown': {}}
    if sec_dir:
        if not os.path.isdir(sec_dir):
            raise ConfigError('SEC keys directory %s does not exist' % sec_dir)
        sec_policy.load_revocations(os.path.join(sec_dir, SEC_FILE))   # malformed: said before any change
    held = None
    if tls_dir:
        if not os.path.isfile(os.path.join(tls_dir, 'ca.tls.key')):
            raise ConfigError('%s is not a TLS authority directory (no ca.tls.key: tls_keygen makes it)' % tls_dir)
        held = _held_list(tls_dir)   # an unusable CA, a corrupt list: said before any change
        tls.issued_serials(tls_dir)
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
    if done['sec'] and not os.access(sec_dir, os.W_OK):
        raise ConfigError('SEC keys directory %s: not writable by this user' % sec_dir)
    if done['tls']:
        if not os.access(tls_dir, os.W_OK):
            raise ConfigError('TLS authority directory %s: not writable by this user' % tls_dir)
        for directory in copy_to:
            _check_copy_dir(directory, tls_dir, (held.number or 0) + 1)
    return done


def revoke(parties, sec_dir=None, tls_dir=None, copy_to=()):
    """Revoke parties in both layers (module docstring). Returns lines saying what was done."""
    parties = list(dict.fromkeys(parties))
    todo = plan(parties, sec_dir, tls_dir, copy_to)
    said = []
    try:
        if todo['sec']:
            path = os.path.join(sec_dir, SEC_FILE)
            with tls.file_lock(path + '.lock'):
                barred = sec_policy.load_revocations(path)
                barred += [p for p in todo['sec'] if p not in barred]
                mode = os.stat(path).st_mode & 0o777 if os.path.exists(path) else 0o644
                tls.write_file(path, yaml.safe_dump({'revoked': barred}, default_flow_style=False).encode(), mode)
            said.append('SEC: %s revoked in %s (the CA refuses the certificates within its status period, 0.5 s)'
                        % (', '.join(todo['sec']), path))
        if todo['tls']:
            path, number = tls.revoke(tls_dir, todo['tls'])   # (under the authority's lock)
            said.append('TLS: %s revoked, list number %d in %s' % (', '.join(todo['tls']), number, path))
            with open(path, 'rb') as f:
                crl = f.read()
            for directory in copy_to:
                tls.write_file(os.path.join(directory, tls.CRL), crl, 0o644)
                said.append('TLS: list %d copied into %s (its nodes cut the revoked connections within a second)'
                            % (number, directory))
            if not copy_to:
                said.append('TLS: copy %s into every party\'s TLS directory' % path)
    except Exception as e:   # the disk, or anything else once writing began: what was done is said
        raise Incomplete(said, e)
    for party, layers in sorted(todo['unknown'].items()):
        said.append('%s: not a %s party, not revoked there' % (party, ' or '.join(layers)))
    return said
