"""The ``px4-dds`` link: PX4's uXRCE-DDS topics spoken directly through Cyclone DDS (no ROS
install), and a stand-in for PX4's DDS side in front of the simulated PX4."""
