"""Scene directories: writing them (``undream init``) and their verification renders."""
