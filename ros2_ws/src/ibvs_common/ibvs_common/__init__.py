"""The base every IBVS package depends on: shared geometry, configuration and node helpers.

``ibvs_common.core`` is ROS-free (numpy/OpenCV, dataclasses in and out): frames and
conversions, the camera model, the paper's feature geometry, the attitude buffer, the loaders
of the vehicle, camera and pad-layout YAML files, and the OpenCV 4.6 / >= 4.7 compatibility
layer. The modules at the top level are the rclpy helpers every node uses: QoS and message
conversions (node_common), parameter descriptors, the spin loop and the throttled log.
Nothing here imports ibvs_control, ibvs_perception or ibvs_sim.
"""
