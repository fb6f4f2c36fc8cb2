def simulated_roots(): pass
def available_species(): pass
