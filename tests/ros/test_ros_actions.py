"""ros_actions.GoalClient against a real action server (same process, private context): a goal whose
response is lost (Fast DDS drops a response to a reader the server has not matched yet) is taken
from the server's goal status; a rejected goal whose response is lost is re-sent and rejected again."""
import pytest

pytestmark = pytest.mark.ros


def test_goal_client_survives_lost_goal_responses(ros_node):
    from rclpy.action import ActionServer, GoalResponse
    from rclpy.task import Future

    from metro_msgs.action import DriveProbe
    from ros_actions import GoalClient

    executed = []

    def execute(gh):
        executed.append(bytes(gh.goal_id.uuid))
        gh.succeed()
        return DriveProbe.Result(success=True, message=f"done {len(executed)}")

    ActionServer(ros_node, DriveProbe, "/test_actions/drive", execute,
                 goal_callback=lambda g: GoalResponse.REJECT if g.mode == "bad" else GoalResponse.ACCEPT)
    client = GoalClient(ros_node, DriveProbe, "/test_actions/drive")
    assert client.wait_for_server(timeout=20)

    def result(gh):
        rf = gh.get_result_async()
        assert ros_node.spin_until(rf.done, timeout=20)
        return rf.result().result

    gh = client.send_goal(DriveProbe.Goal(mode="direct"), timeout=20)
    assert gh.accepted and result(gh).message == "done 1" and client.recovered == client.resent == 0

    send = client.client.send_goal_async
    lost = []

    def lose_first_response(goal, **kw):
        fut = send(goal, **kw)                  # the request goes out and the server answers ...
        if lost:
            return fut
        lost.append(fut)
        return Future()                         # ... but this client never hears it

    client.client.send_goal_async = lose_first_response
    gh = client.send_goal(DriveProbe.Goal(mode="direct"), timeout=20, response_timeout=1.0)
    assert gh is not None and gh.accepted and client.recovered == 1 and client.resent == 0
    assert result(gh).message == "done 2" and len(executed) == 2 and executed[-1] == bytes(gh.goal_id.uuid)

    lost.clear()
    gh = client.send_goal(DriveProbe.Goal(mode="bad"), timeout=20, response_timeout=1.0)
    assert gh is not None and not gh.accepted and client.resent == 1 and len(executed) == 2
