"""btmission's built-in capability libraries (installed as ``btmission_library``).

Each library is a YAML spec plus a Python module of implementations, registered through the
``btmission.libraries`` entry-point group exactly as a third-party plugin would be.
"""
