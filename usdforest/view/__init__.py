"""Pictures: the headless stage renderer behind ``usdforest preview`` and the figures of
sites and skeletons."""
