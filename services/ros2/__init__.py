"""ROS 2 without ROS, the pure half (no Zenoh): rmw_zenoh's names, keys and tokens (`wire`), message types,
hashes and CDR (`typesupport`, rosbags'), the bridge's interface (`interface`) and its core (`bridge`).
The Zenoh half is the shell's (`services.shell.ros2`) and the bag player the application's
(`cvxnav.ros2_play`)."""
