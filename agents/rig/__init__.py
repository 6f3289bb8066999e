"""The rig side: rollouts on a device with safety stops and logs (``rollout``) and plant
identification from a rollout log (``identify``)."""
