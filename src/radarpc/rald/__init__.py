"""radarpc.rald"""
