"""Frame-to-map tracking: plane and corner association, closed-form registration,
relocalisation, RGB-D odometry and ICP fallbacks (`tracker.Tracker`)."""
