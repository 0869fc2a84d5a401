"""rosrun aft_ftm rejoin SITE [--launch 'COMMAND' [--launch-tls-dir DIR]] [--takeover S] [--timeout S] [--witness SERVICE]

Brings a replica site back into its PBR pair: optionally starts it (COMMAND, e.g. its roslaunch,
detached in a session of its own so that it outlives this command), then waits until the witness
names SITE the backup of the serving primary, which happens once its state transfer is
acknowledged. A site re-joins by itself when it starts; this command tells when it has. A site the
witness still names the primary is never launched: with --takeover S it waits up to S seconds for
its backup to take over (right after the primary failed, before its peer's verdict), then launches.
Under mutual TLS (AFT_TLS_DIR, the caller's party: the witness answers TLS only) the command
launched must run as the site's party, never as the caller's: --launch-tls-dir names the site's TLS
directory (its party is the one whose key is there), required with --launch under TLS.
Exit status: 0 re-joined (or, without --launch, SITE is the primary), 1 not within the timeout or
SITE still the primary with --launch (nothing started), 2 bad use or no witness.
"""
import argparse
import os
import shlex
import subprocess
import sys
import time

import rospy
from aft_msgs.srv import Witness

from .. import tls
from ..errors import ConfigError
from ..where import WhereError, site_tls
from ..witness import Op
from .witness_client import DEFAULT_WITNESS


def status(service):
    return rospy.ServiceProxy(service, Witness)(op=Op.STATUS.value, site='rejoin')


def launch_environment(site, launch, tls_dir, environ):
    """The environment of the launched command: environ, with the site's TLS party (from tls_dir) under
    TLS. ConfigError when the command would run as the caller's party (under TLS without tls_dir), or
    tls_dir is given without TLS or without --launch, holds the CA's key or no one party's pair, or its
    party may not run the site's nodes (/SITE/*) under this command's policy, or its certificate is not
    one this command's CA signed for that party, valid now (aft_ftm.where.site_tls)."""
    env = dict(environ)
    if tls_dir and not launch:
        raise ConfigError('--launch-tls-dir is for the command --launch starts: none is given')
    if not tls_dir:
        if launch and env.get('AFT_TLS_DIR'):
            raise ConfigError('under TLS (AFT_TLS_DIR=%s, party %s) the site launched would run as this command\'s '
                              'party: give its own TLS directory with --launch-tls-dir (also when the command\'s '
                              'own arguments set its TLS); nothing started' % (env['AFT_TLS_DIR'], env.get('AFT_TLS_PARTY')))
        return env
    if not env.get('AFT_TLS_DIR') or not env.get('AFT_TLS_POLICY'):
        raise ConfigError('--launch-tls-dir %s without TLS here (AFT_TLS_DIR and AFT_TLS_POLICY unset): the witness '
                          'of a TLS deployment answers TLS only' % tls_dir)
    name = site.strip('/')
    if not name or not all(c.isalnum() or c in '_-' for c in name):
        raise ConfigError('site %r: a site name is letters, digits, - or _' % site)
    if os.path.exists(os.path.join(tls_dir, 'ca.tls.key')):
        raise ConfigError('--launch-tls-dir %s holds the CA\'s private key: give the site party\'s own directory '
                          '(tls_keygen\'s export), never the authority\'s; nothing started' % tls_dir)
    party = tls.party_of_directory(tls_dir)
    try:
        chosen = site_tls({'AFT_TLS_DIR': tls_dir, 'AFT_TLS_PARTY': party}, os.getcwd(), ['/%s/recovery' % name], env)
    except WhereError as e:
        raise ConfigError('--launch-tls-dir %s: %s (the site\'s nodes are /%s/*); nothing started' % (tls_dir, e, name))
    env.update(chosen)
    return env


def main(argv):
    parser = argparse.ArgumentParser(prog='rejoin', description=__doc__.split('\n\n')[1])
    parser.add_argument('site')
    parser.add_argument('--launch', default='', help='command that starts the site (e.g. its roslaunch)')
    parser.add_argument('--timeout', type=float, default=60.0, help='seconds to wait for the join (60)')
    parser.add_argument('--witness', default=None,
                        help="the witness service (default: the one the site's Recovery follows, its parameter "
                             "/SITE/recovery/witness, else /aft/witness/request)")
    parser.add_argument('--takeover', type=float, default=0.0,
                        help='with --launch, seconds to wait for another site to become the primary (0)')
    parser.add_argument('--launch-tls-dir', default='',
                        help="under TLS: the site's TLS directory, whose party the launched command runs as")
    args = parser.parse_args(rospy.myargv(argv))
    try:
        launch_env = launch_environment(args.site, args.launch, args.launch_tls_dir, os.environ)
        from .params import secure_from_environment
        secure_from_environment()   # mutual TLS where AFT_TLS_DIR says so: the witness answers TLS only then
    except ConfigError as e:
        print('rejoin: %s' % e, file=sys.stderr)
        return 2
    rospy.init_node('rejoin', anonymous=True, disable_signals=True)   # a name its party's nodes allow
    if args.witness is None:
        # The site's own witness: with several services on one master, the default one is another's,
        # which never names this site primary, so a site still serving was launched over (review of
        # session 40). The parameter outlives the Recovery node.
        try:
            args.witness = rospy.get_param('/%s/recovery/witness' % args.site.strip('/'), DEFAULT_WITNESS)
        except (rospy.ROSException, OSError) as e:
            print('rejoin: the ROS master cannot be asked for the witness of %s: %s' % (args.site, e), file=sys.stderr)
            return 2
        if not args.witness or args.witness == 'none':
            print('rejoin: %s\'s Recovery follows no witness (its ~witness is empty): nothing tells a re-join; '
                  'give --witness' % args.site, file=sys.stderr)
            return 2
        print('rejoin: the witness of %s: %s' % (args.site, args.witness))
    try:
        rospy.wait_for_service(args.witness, 5.0)
        before = status(args.witness)
        if before.primary == args.site and args.launch and args.takeover > 0:
            print('rejoin: %s is still the primary of epoch %d: waiting up to %.0f s for its backup to take over'
                  % (args.site, before.epoch, args.takeover))
            deadline = time.monotonic() + args.takeover
            while before.primary == args.site and time.monotonic() < deadline:
                time.sleep(0.05)
                before = status(args.witness)
    except (rospy.ROSException, rospy.ServiceException) as e:
        print('rejoin: the witness %s cannot be reached: %s' % (args.witness, e), file=sys.stderr)
        return 2
    if before.primary == args.site and args.launch:
        # Not launched, and said as a failure (review of the witness, session 33: it exited 0 having
        # started nothing, right after the primary failed). A site launched while it still serves would
        # replace its running nodes; one that failed re-joins once its peer took over.
        print('rejoin: %s is still the primary of epoch %d for the witness: not launched. If it failed, its '
              'backup takes over once its crash detector declares it (the witness then names another '
              'primary): run this again then, or give --takeover. A primary alone that failed cannot be replaced by its own '
              'restart (it holds no state); see the README, "When the failed site comes back"'
              % (args.site, before.epoch), file=sys.stderr)
        return 1
    if before.primary == args.site:
        print('rejoin: %s is the primary of epoch %d: nothing to re-join' % (args.site, before.epoch))
        return 0
    started = time.monotonic()
    if args.launch:
        subprocess.Popen(shlex.split(args.launch), start_new_session=True, stdin=subprocess.DEVNULL,
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=launch_env)
        print('rejoin: started %s' % args.launch)
    print('rejoin: waiting for %s to join %s (epoch %d)' % (args.site, before.primary, before.epoch))
    now = None
    while time.monotonic() - started < args.timeout:
        try:
            now = status(args.witness)
        except rospy.ServiceException:
            now = None
        if now is not None and now.backup == args.site:
            print('rejoin: %s is the backup of %s at epoch %d, %.2f s after the start'
                  % (args.site, now.primary, now.epoch, time.monotonic() - started))
            return 0
        time.sleep(0.05)
    print('rejoin: %s did not re-join within %.0f s (witness: epoch %d, primary %r, backup %r)'
          % (args.site, args.timeout, now.epoch if now else 0, now.primary if now else '', now.backup if now else ''),
          file=sys.stderr)
    return 1
