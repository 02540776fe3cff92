"""motok.sim"""
