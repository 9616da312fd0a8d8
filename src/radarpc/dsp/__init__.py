"""radarpc.dsp"""
