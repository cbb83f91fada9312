"""Feature-only (D-SLAM) maps (Linear SLAM Sec. 7, App. B): features in frames defined by features.

``maps`` holds the map value, ``frames`` the feature-defined frames, ``conversion`` the
pose-feature to feature-only marginalisation, ``precondition`` the grouping of Sec. 8.3,
``joining`` the linear joins, ``refine`` the feature-only Nonlinear LS and ``online`` the
streaming state the joiner's feature-only strategies use.
"""
