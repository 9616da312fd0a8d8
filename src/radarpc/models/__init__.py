"""radarpc.models"""
