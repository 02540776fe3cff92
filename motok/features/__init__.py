"""motok.features"""
