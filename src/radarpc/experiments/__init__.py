"""radarpc.experiments"""
