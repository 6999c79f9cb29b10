"""An action client for tests that survives a lost goal response.

Fast DDS drops a service response when the server's response writer has not yet matched the
client's response reader (the server logs "failed to send response (timeout): client will not
receive response"). Discovery is asymmetric: ``server_is_ready()`` says the client has matched the
server, not that the server has matched the client, so the first goal right after it can be
accepted and executed while ``send_goal_async``'s future never completes (seen in 1 of 6
fresh-clone CI runs of test_picms_targeting_node).

``GoalClient.send_goal`` gives every goal a known UUID and, when no response comes within
``response_timeout``, asks the server's goal status topic (reliable, transient local: it reaches
a late-matched reader) whether the goal was taken: if so, the goal handle is made from the UUID
(result, cancel and feedback work by UUID). With no status either, the request is sent again with
the same UUID: a server that never saw it takes it now; one that rejected it rejects it again and
this time the response arrives; one that accepted it answers "duplicate", and the status decides.
"""
from __future__ import annotations

import time
import uuid

from action_msgs.msg import GoalStatus, GoalStatusArray
from rclpy.action import ActionClient
from rclpy.action.client import ClientGoalHandle
from rclpy.qos import qos_profile_action_status_default
from unique_identifier_msgs.msg import UUID

TAKEN = (GoalStatus.STATUS_ACCEPTED, GoalStatus.STATUS_EXECUTING, GoalStatus.STATUS_CANCELING,
         GoalStatus.STATUS_SUCCEEDED, GoalStatus.STATUS_CANCELED, GoalStatus.STATUS_ABORTED)


class GoalClient:
    """``ActionClient`` of ``node`` (which has ``spin_until(pred, timeout)``, the ros_node fixture)."""

    def __init__(self, node, action_type, name: str):
        self.node, self.action_type = node, action_type
        self.client = ActionClient(node, action_type, name)
        self.status = {}                 # goal UUID bytes -> (GoalStatus code, acceptance stamp)
        self.recovered = 0               # goals whose response was lost and taken from the status topic
        self.resent = 0
        node.create_subscription(GoalStatusArray, name.rstrip("/") + "/_action/status", self._on_status,
                                 qos_profile_action_status_default)

    def _on_status(self, msg):
        for s in msg.status_list:
            self.status[bytes(s.goal_info.goal_id.uuid)] = (s.status, s.goal_info.stamp)

    def wait_for_server(self, timeout: float) -> bool:
        return self.node.spin_until(self.client.server_is_ready, timeout=timeout)

    def _taken(self, key):
        st = self.status.get(key)
        return st is not None and st[0] in TAKEN

    def send_goal(self, goal, feedback_callback=None, timeout: float = 30.0, response_timeout: float = 3.0):
        """The goal's ClientGoalHandle (``accepted`` True or False), or None when the server neither
        answered nor took the goal within ``timeout``."""
        goal_id = UUID(uuid=list(uuid.uuid4().bytes))
        key = bytes(goal_id.uuid)
        t_end = time.monotonic() + timeout
        futures = [self.client.send_goal_async(goal, feedback_callback=feedback_callback, goal_uuid=goal_id)]
        while time.monotonic() < t_end:
            wait = min(response_timeout, t_end - time.monotonic())
            self.node.spin_until(lambda: any(f.done() for f in futures) or self._taken(key), timeout=wait)
            answers = [f.result() for f in futures if f.done()]
            if any(gh.accepted for gh in answers):
                return next(gh for gh in answers if gh.accepted)
            if self._taken(key):         # accepted, but the response was lost (or said "duplicate")
                self.recovered += 1
                response = self.action_type.Impl.SendGoalService.Response(accepted=True, stamp=self.status[key][1])
                return ClientGoalHandle(self.client, goal_id, response)
            if answers:
                # rejected (or, for a re-send, "duplicate" of a goal taken whose status has not come
                # yet: an accepted goal publishes its status at once, so give it a moment)
                if not self.node.spin_until(lambda: self._taken(key), timeout=min(1.0, response_timeout)):
                    return answers[-1]
                continue
            if time.monotonic() < t_end:
                self.resent += 1
                futures.append(self.client.send_goal_async(goal, feedback_callback=feedback_callback,
                                                           goal_uuid=goal_id))
        return None
