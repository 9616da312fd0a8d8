"""radarpc.eval"""
