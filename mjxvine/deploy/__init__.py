"""The trained actor on the robot: the numpy policy and its file, and the exporters.

    from mjxvine.deploy import NumpyPolicy        # numpy only: no jax, flax, mujoco
    policy = NumpyPolicy.load("policy.npz")

`numpy_policy` is the whole numpy policy (imports only numpy and the standard library; copy
that one file to a robot). `export` writes a run's actor as such a file, `onnx` as an ONNX
graph, `latency` times one decision; they import jax or onnx, so they are not imported here.
`node_logic` is the ROS 2 node's checks and decisions without ROS (numpy and
`numpy_policy` only).
"""

from mjxvine.deploy.numpy_policy import (FORMAT_VERSION, META_KEY, MIRROR_ACTION_SIGN,
                                         MIRROR_STATE_SIGN, ROS_DEPTH_ENCODINGS, NumpyPolicy,
                                         PolicyError, PolicyFormatError, PolicyInputError,
                                         RowEnd, band_rows, depth_from_ros, fov_window,
                                         policy_layout, read_policy_file, ros_depth_to_metres,
                                         row_cue, row_start, row_update, set_blas_threads)

__all__ = ["FORMAT_VERSION", "META_KEY", "MIRROR_ACTION_SIGN", "MIRROR_STATE_SIGN",
           "ROS_DEPTH_ENCODINGS", "NumpyPolicy", "PolicyError", "PolicyFormatError",
           "PolicyInputError", "RowEnd", "band_rows", "depth_from_ros", "fov_window",
           "policy_layout", "read_policy_file", "ros_depth_to_metres", "row_cue", "row_start",
           "row_update", "set_blas_threads"]
