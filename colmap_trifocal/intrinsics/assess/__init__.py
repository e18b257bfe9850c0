"""The assessment, the final solve → the camera's result: std, what is determined, where
each value comes from (``assessment``), and why the rest is not (``diagnosis``).
"""
