"""Survey missions: the paper's rectangle and its export as a plan any ground station loads."""
