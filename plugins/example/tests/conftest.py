pytest_plugins = ["occplug.testing"]
