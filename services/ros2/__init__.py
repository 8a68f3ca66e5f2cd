"""The ROS 2 robot backend: rmw_zenoh's wire format (types, wire, rmw) without ROS 2 installed."""
