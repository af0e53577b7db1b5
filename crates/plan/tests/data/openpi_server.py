"""A policy server speaking openpi's websocket protocol, for the served-policy tests.

Written as openpi's own `WebsocketPolicyServer` behaves (openpi/serving/
websocket_policy_server.py): on connect it sends its metadata packed with
`openpi_client.msgpack_numpy`; per message it unpacks the observation, answers
with a map holding "actions" `[steps, 7]`, or with the traceback as a text
message when inference fails. It prints the port it listens on, then serves.

Modes (--mode) make the failures the client must name:
  good         absolute end-effector actions: the observed pose moved +1 cm in x per step
  delta        the same as deltas from the observed pose
  joints       the observed arm joints and gripper, [steps, 8] (joint positions)
  joint_velocity  0.1 rad/s on the first joint, [steps, 8] (joint velocities)
  wrong_shape  "actions" of shape [steps, 6]
  non_finite   a NaN in row 1, column 2
  strings      "actions" holding a string array's bytes as dtype <U4
  slow         answers after --delay seconds
  close        closes the connection on the first observation
  error        answers with a traceback text (inference raised)
The observation is checked (image uint8 [224, 224, 3] or the configured size,
float64 joints [7], gripper [1], end-effector pose [6], prompt string); a bad
one is answered with an error text naming the key.
"""

import argparse
import sys
import time
import traceback

import numpy as np
from openpi_client import msgpack_numpy
from websockets.sync.server import serve

parser = argparse.ArgumentParser()
parser.add_argument("--mode", default="good")
parser.add_argument("--delay", type=float, default=5.0)
parser.add_argument("--steps", type=int, default=4)
parser.add_argument("--image-size", type=int, nargs=2, default=[224, 224])
args = parser.parse_args()


def check(obs):
    h, w = args.image_size
    img = obs["observation/exterior_image_1_left"]
    assert img.dtype == np.uint8 and img.shape == (h, w, 3), f"image {img.dtype} {img.shape}"
    wrist = obs["observation/wrist_image_left"]
    assert wrist.shape == (h, w, 3) and not wrist.any(), "wrist image: expected black"
    q = obs["observation/joint_position"]
    assert q.dtype == np.float64 and q.shape == (7,), f"joints {q.dtype} {q.shape}"
    g = obs["observation/gripper_position"]
    assert g.shape == (1,), f"gripper {g.shape}"
    pose = obs["observation/ee_pose"]
    assert pose.shape == (6,), f"ee_pose {pose.shape}"
    assert isinstance(obs["prompt"], str), "prompt: expected a string"
    return pose, float(g[0]), q


def infer(obs):
    pose, grip, q = check(obs)
    n = args.steps
    if args.mode in ("joints", "joint_velocity"):
        rows = np.zeros((n, 8))
        if args.mode == "joints":
            rows[:, :7] = q
        else:
            rows[:, 0] = 0.1
        rows[:, 7] = grip
        return {"actions": rows}
    rows = np.zeros((n, 7))
    for i in range(n):
        rows[i, :6] = pose
        rows[i, 0] += 0.01 * (i + 1)
        rows[i, 6] = grip
    if args.mode == "delta":
        rows[:, :6] -= pose
    if args.mode == "wrong_shape":
        rows = rows[:, :6]
    if args.mode == "non_finite":
        rows[1, 2] = np.nan
    if args.mode == "strings":
        return {"actions": np.array(["a", "b"])}
    return {"actions": rows.astype(np.float32), "policy_timing": {"infer_ms": 1.0}}


def handler(ws):
    packer = msgpack_numpy.Packer()
    ws.send(packer.pack({"policy": "test", "mode": args.mode, "action_horizon": args.steps}))
    while True:
        try:
            obs = msgpack_numpy.unpackb(ws.recv())
        except Exception:
            return
        if args.mode == "close":
            ws.close()
            return
        if args.mode == "slow":
            time.sleep(args.delay)
        try:
            if args.mode == "error":
                raise RuntimeError("inference failed on purpose")
            action = infer(obs)
        except Exception:
            ws.send(traceback.format_exc())
            continue
        ws.send(packer.pack(action))


with serve(handler, "127.0.0.1", 0, compression=None, max_size=None) as server:
    print(server.socket.getsockname()[1], flush=True)
    server.serve_forever()
