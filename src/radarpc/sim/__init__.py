"""radarpc.sim"""
