"""ROS-free core of beo_ros: arrays in, arrays out. Never imports rclpy or message packages."""
