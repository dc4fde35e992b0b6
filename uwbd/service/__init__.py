"""The robot's service: serial sources, the pipeline, Zenoh, systemd, the demo and echo."""
