"""The live loop: a projector window, a camera client, and the device that ties them with a measured latency."""
