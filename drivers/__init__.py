"""The C-arm link: encoder protocol, serial driver, kinematics and the simulated C-arm."""
