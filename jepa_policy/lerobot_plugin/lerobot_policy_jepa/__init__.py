"""JEPA Policy as a LeRobot policy type: importing this package registers ``jepa`` with LeRobot.

LeRobot's command lines import it at start-up (``register_third_party_plugins``); LeRobot's factory then finds
``JEPAPolicy`` in ``modeling_jepa`` and ``make_jepa_pre_post_processors`` in ``processor_jepa`` by name.
"""
from lerobot_policy_jepa.configuration_jepa import JEPAConfig

__all__ = ["JEPAConfig"]
