"""
Pure numerical core: phantoms, imaging, tags, registration, meshless model, analysis, io.

Nothing under this package imports rclpy. Units: millimetres, seconds, radians; positions in
DICOM patient coordinates (LPS) unless a docstring says model-centred.
"""
