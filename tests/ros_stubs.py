"""Stub rclpy and ROS message modules, so that tests drive examples/ros2_vineyard_node.py
without ROS: `load_node_module(monkeypatch, params, clock_s)` returns the example's module
whose `VineyardNode` runs on `Node` below (its cmd_vel publisher appends to
`node.published`, every publisher to `node.topics[topic]`)."""

import importlib.util
import sys
import types
from pathlib import Path
from types import SimpleNamespace

NODE_FILE = Path(__file__).resolve().parent.parent / "examples" / "ros2_vineyard_node.py"


class Logger:
  """Records (level, message, kwargs) of every log call."""

  def __init__(self):
    self.records = []

  def _log(self, level, msg, **kw):
    self.records.append((level, msg, kw))

  def error(self, msg, **kw):
    self._log("error", msg, **kw)

  def warn(self, msg, **kw):
    self._log("warn", msg, **kw)

  def info(self, msg, **kw):
    self._log("info", msg, **kw)


class Node:
  """The part of rclpy.node.Node the example uses; `t` is the clock (s)."""
  params: dict = {}
  clock_s = 100.0

  def __init__(self, name):
    self.name, self.t, self.published, self._logger = name, self.clock_s, [], Logger()
    self.topics = {}  # topic -> the messages published on it

  def declare_parameter(self, name, default):
    return SimpleNamespace(value=self.params.get(name, default))

  def get_logger(self):
    return self._logger

  def get_clock(self):
    return SimpleNamespace(now=lambda: SimpleNamespace(nanoseconds=int(self.t * 1e9)))

  def create_publisher(self, msg_type, topic, qos=None):
    def publish(msg):
      self.topics.setdefault(topic, []).append(msg)
      if topic == "cmd_vel":
        self.published.append(msg)
    return SimpleNamespace(publish=publish)

  def create_service(self, *args):
    pass

  def create_subscription(self, *args):
    pass

  def create_timer(self, *args):
    pass


class Twist:
  def __init__(self):
    self.linear = SimpleNamespace(x=0.0, y=0.0, z=0.0)
    self.angular = SimpleNamespace(x=0.0, y=0.0, z=0.0)


class Bool:
  def __init__(self, data=False):
    self.data = data


def load_node_module(monkeypatch, params: dict, clock_s: float = 100.0):
  """The example node's module, imported on stub rclpy and message modules (undone by
  `monkeypatch`); its nodes read `params` and start their clock at `clock_s`."""
  def module(name, **attrs):
    mod = types.ModuleType(name)
    mod.__dict__.update(attrs)
    monkeypatch.setitem(sys.modules, name, mod)

  module("rclpy", init=lambda args=None: None, spin=lambda node: None,
         try_shutdown=lambda: None)
  module("rclpy.node", Node=Node)
  module("rclpy.qos", qos_profile_sensor_data=None)
  module("sensor_msgs")
  module("sensor_msgs.msg", CameraInfo=object, Image=object, Imu=object)
  module("geometry_msgs")
  module("geometry_msgs.msg", Twist=Twist)
  module("std_msgs")
  module("std_msgs.msg", Bool=Bool)
  module("std_srvs")
  module("std_srvs.srv", Trigger=object)
  monkeypatch.setattr(Node, "params", params)
  monkeypatch.setattr(Node, "clock_s", clock_s)
  spec = importlib.util.spec_from_file_location("ros2_vineyard_node", NODE_FILE)
  mod = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(mod)
  return mod
