"""Navigation on occupancy grids: geodesic fields (navigation, numpy, offline), their jittable
lookups and descent chains (planning), and the imitation expert's decisions on them (expert).
"""
