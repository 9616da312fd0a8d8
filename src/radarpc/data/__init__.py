"""radarpc.data"""
