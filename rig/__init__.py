"""rig: a real-time controller runtime for an electro-hydraulic vibration-isolation rig (Law et al., CIRP 2015).

`import rig` is light (the names differ from the submodules rig.identify and rig.diagnose on purpose): the API's functions (rig/api.py) load what they need when first used.
"""

_API = ("load_recording", "record_chirp", "identify_actuator", "diagnose_recording", "simulate_isolation", "IsolationComparison",
        "SuspectFit")
__all__ = list(_API)


def __getattr__(name: str):
    if name in _API:
        from rig import api        # lazy: `import rig` loads nothing heavy until an API function is used
        return getattr(api, name)
    raise AttributeError(f"module 'rig' has no attribute {name!r}")
