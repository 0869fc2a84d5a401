"""The campaign's clients get their seed as a ROS parameter: it must stay an XML-RPC int. No ROS master."""
import xmlrpc.client

import pytest

from aft_examples.ros.campaign import CampaignDeployment, client_seed


@pytest.mark.parametrize('schedule_seed', [0, 21474, 21475, 99999, 10 ** 9])
def test_every_client_seed_is_an_xml_rpc_int_and_clients_differ(schedule_seed):
    segment_seed = schedule_seed * 1000 + 39          # scripts/campaign: seed * 1000 + segment
    deployment = CampaignDeployment('/tmp/aft_unit_campaign', clients=3, seed=segment_seed)
    seeds = []
    for name, argv in sorted(deployment.client_argv.items()):
        value = int(next(a for a in argv if a.startswith('_seed:=')).split(':=')[1])
        xmlrpc.client.dumps((value,))                 # raises OverflowError past the XML-RPC limit
        seeds.append(value)
    assert len(set(seeds)) == 3 and seeds == [client_seed(segment_seed, k) for k in (1, 2, 3)]
