"""An example occplug plugin: a tiny MLP occupancy head."""

__version__ = "0.1.0"
