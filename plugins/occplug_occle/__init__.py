"""occplug-occle: OccLE (label-efficient occupancy with decoupled semantic and geometric branches) as occplug
components.

Work in progress: the building blocks below are tested; the components, configs and the ``occplug`` entry point
come with the plugin's model.
"""
